"""docs/tuner.md's metrics table is complete and exact: every ``pitune_*`` family a
started tuner exposes (a cluster member on a real PostgreSQL store, and a lone tuner on
SQLite) has its row with the same type and labels, and every row is exposed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from service.daemon.api import create_app
from tests.tuner_support import tuner_settings

pytestmark = pytest.mark.timeout(90)
DOC = Path(__file__).parent.parent / "docs" / "tuner.md"
ROW = re.compile(r"^\| `(pitune_\w+)` \| (\w+) \|([^|]*)\| (.+) \|$")
CLUSTER_ONLY = "Cluster only:"


def _table() -> dict[str, tuple[str, set[str], bool]]:
    """Family name (a counter's without ``_total``) -> (type, labels, cluster only)."""
    text = DOC.read_text()
    section = text[text.index("\n## Metrics\n") + 1 :]
    section = section.split("\n## ", 1)[0]  # up to the next section, if any
    rows = {}
    for line in section.splitlines():
        m = ROW.match(line)
        if m is None:
            continue
        name, kind, labels, meaning = m.groups()
        assert (kind == "counter") == name.endswith("_total"), line
        family = name.removesuffix("_total") if kind == "counter" else name
        assert family not in rows, f"{name} twice"
        labels = set(re.findall(r"`(\w+)`", labels))
        rows[family] = (kind, labels, meaning.startswith(CLUSTER_ONLY))
    assert len(rows) > 20, "the table's rows were not found"
    return rows


def _exposed(settings) -> dict[str, tuple[str, set[str] | None]]:
    """Family -> (type, label names; None when it has no sample to show them)."""
    with TestClient(create_app(settings)) as client:
        text = client.get("/metrics").text
    families = {}
    for family in text_string_to_metric_families(text):
        if family.name.startswith("pitune_"):
            labels = {k for s in family.samples for k in s.labels if k != "le"}
            families[family.name] = (family.type, labels if family.samples else None)
    return families


def _check(exposed, table) -> None:
    assert set(exposed) == set(table)
    for name, (kind, labels) in exposed.items():
        assert kind == table[name][0], name
        assert labels is None or labels == table[name][1], name


def test_the_table_is_what_a_cluster_member_exposes(tmp_path, pg_url):
    table = _table()
    _check(_exposed(tuner_settings(tmp_path, db_path=pg_url, instance_id="m1")), table)


def test_the_table_less_its_cluster_rows_is_what_a_lone_tuner_exposes(tmp_path):
    table = {name: row for name, row in _table().items() if not row[2]}
    _check(_exposed(tuner_settings(tmp_path)), table)
