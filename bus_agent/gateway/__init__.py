"""The agent's Zenoh side: the gateway (:mod:`.gateway`), the bridge that runs it in a child
process (:mod:`.bridge`), leases (:mod:`.leases`) and the Zenoh session configuration
(:mod:`.zenoh_config`)."""
