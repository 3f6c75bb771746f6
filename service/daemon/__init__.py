"""The tuner daemon: the tuning engine behind a Zenoh bus, a store (SQLite, or PostgreSQL
shared by several tuners) and a REST API."""
