"""The CANopen backend: CiA 402 drives on a CAN bus behind the same Bus interface as EtherCAT.

One module per CANopen service (CiA 301), as python-canopen arranges them: ``nmt`` (commands,
states, the NMT slave transition table), ``heartbeat`` (the consumer), ``emcy`` (decoding),
``cob`` (the pre-defined connection set), ``sdo`` (an adapter over python-canopen's SDO client),
``pdo`` (the process image on the shared ``bus_agent.bus.mapping`` / ``codec``, its policies and
frames), and ``bus`` (:class:`~bus_agent.bus.canopen.bus.CanopenBus`, the Bus protocol).
``nmt``, ``heartbeat``, ``emcy`` and ``cob`` are pure (no I/O); the simulator
(``bus_agent.sim.canopen``) uses them for the device side too.
"""
