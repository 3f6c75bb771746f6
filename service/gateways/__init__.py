"""Gateways between a plant's control system and the pitune bus (``pitune gateway ...``)."""
