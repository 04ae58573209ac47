"""Virtual EtherCAT segment (``ecat-sim``): ESCs with SII, SMs, FMMUs, AL states and CoE,
answering unmodified SOEM/pysoem over a raw socket. See docs/virtual-ethercat.md."""
