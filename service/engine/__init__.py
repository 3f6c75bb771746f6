"""The bus-free tuning engine (see :mod:`service.engine.engine`)."""
