"""The OPC UA gateway: a DCS's PID blocks on one side, the pitune bus on the other.

* :mod:`.forms`: the PID blocks' gain forms and their conversions to pitune's parallel form;
* :mod:`.sitemap`: the map file (TOML): server, security, bus, and one entry per loop;
* :mod:`.certs`: self-signed client certificates (``pitune gateway certs``);
* :mod:`.client`: the asyncua side (secure session, monitored items, write and read back);
* :mod:`.loops`: each loop's runtime view (values, pending update) and the write policy;
* :mod:`.bridge`: the gateway itself (samples out, gains in, writes, reconnects);
* :mod:`.register`: the bulk registration of the map's loops with the tuner;
* :mod:`.cli`: ``pitune gateway opcua --map site.toml``.

See ``docs/opcua.md``.
"""
