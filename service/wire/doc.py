"""Keep the JSON Schemas in ``docs/protocol.md`` generated from :mod:`service.wire.protocol`.

The document's prose is written by hand; the block between the two markers is
generated. Regenerate after changing a wire model::

    python -m service.wire.doc docs/protocol.md

``tests/test_tuner_protocol.py`` fails while the block is out of date.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pydantic import BaseModel

from service.wire.protocol import WIRE_MODELS

BEGIN = "<!-- BEGIN GENERATED SCHEMAS (python -m service.wire.doc docs/protocol.md) -->"
END = "<!-- END GENERATED SCHEMAS -->"


def render_schemas(models: tuple[type[BaseModel], ...] = WIRE_MODELS) -> str:
    """Markdown sections with each model's JSON Schema (validation mode)."""
    parts = []
    for model in models:
        schema = json.dumps(model.model_json_schema(), indent=2, sort_keys=True)
        parts.append(f"### {model.__name__}\n\n```json\n{schema}\n```\n")
    return "\n".join(parts)


def generated_block(text: str) -> str:
    """The generated part of a document (between the markers, exclusive)."""
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[start:end].strip("\n")


def update(path: Path) -> bool:
    """Rewrite the generated block of ``path``; True if it changed."""
    text = path.read_text()
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    new = f"{text[:start]}\n\n{render_schemas()}\n{text[end:]}"
    path.write_text(new)
    return new != text


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0] if args else "docs/protocol.md")
    print(f"{path}: {'updated' if update(path) else 'up to date'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
