"""``canopen-sim``: CANopen CiA 402 drive nodes on a CAN bus (python-can), on the drive model
the other simulators use. ``od`` builds the object dictionary (and an EDS file), ``node`` is one
node's device side (NMT slave, SDO server, SYNC, PDOs, heartbeat, EMCY), ``segment`` runs the
nodes of one bus, ``cli`` is the command. See docs/canopen.md.
"""
