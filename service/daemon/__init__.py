"""The tuner daemon: the tuning engine behind a Zenoh bus, an SQLite or PostgreSQL store and a REST API."""
