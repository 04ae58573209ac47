"""The agent's Zenoh side: the gateway (:mod:`.gateway`, the owner of its parts: :mod:`.commands`,
:mod:`.publisher`, :mod:`.peers`, :mod:`.hostclaim`, :mod:`.recording`, over the hand-offs of
:mod:`.handoff` and the :mod:`.settings`), the bridge that runs it in a child process
(:mod:`.bridge`), leases (:mod:`.leases`) and the Zenoh session configuration (:mod:`.zenoh_config`)."""
