"""The console's static assets (vendored, no CDN), served from the package's static/."""

from __future__ import annotations

from functools import cache
from importlib import resources

_TYPES = {".js": "text/javascript", ".css": "text/css", ".txt": "text/plain", "": "text/plain"}


@cache
def asset(path: str) -> tuple[bytes, str] | None:
    """A file under static/ (no '..', no hidden files), with its content type."""
    parts = path.split("/")
    if any(not p or p.startswith(".") for p in parts):
        return None
    node = resources.files(__package__).joinpath("static", *parts)
    if not node.is_file():
        return None
    suffix = "." + parts[-1].rsplit(".", 1)[1] if "." in parts[-1] else ""
    kind = _TYPES.get(suffix)
    if kind is None:
        return None
    return node.read_bytes(), kind
