"""Vendors' device-description files: ESI (EtherCAT) and EDS (CANopen)."""
