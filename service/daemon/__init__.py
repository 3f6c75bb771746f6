"""The tuner daemon: the tuning engine behind a Zenoh bus, a SQLite store and a REST API."""
