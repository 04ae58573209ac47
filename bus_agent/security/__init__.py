"""Security of the drive network: roles and the ACL they compile to (``roles``), the
principals file (``principals``), the certificate authority and ``drives-pki`` (``pki``,
``cli``). The Zenoh side (TLS links, loading the ACL) is ``bus_agent.gateway.zenoh_config``."""
