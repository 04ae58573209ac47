"""Vendors' device-description files (ESI for EtherCAT, EDS for CANopen): pure parsers."""
