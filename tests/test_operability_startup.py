"""``pitune tuner`` start-up failures (issue 17): each is ONE line on stderr that says
what failed and what to do, with the documented exit status; one tuner per store."""

import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from service.daemon import main as daemon
from service.daemon.store import EpochAheadError, Store
from service.daemon.tuner import Tuner
from service.procs import ROOT, TunerProcess, clean_env, pitune
from service.wire.session import free_port
from tests.tuner_support import open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(120)


def start(tmp_path: Path, *args: str, timeout: float = 90.0, **env: str):
    """``pitune tuner`` on free ports with an untrained agent, and ``args``: the result."""
    argv = pitune(
        "tuner", "--agent-weights", "untrained", "--api-port", str(free_port()),
        "--listen", f"tcp/127.0.0.1:{free_port()}", "--db", str(tmp_path / "pitune.db"), *args,
    )  # fmt: skip
    return subprocess.run(
        argv, cwd=ROOT, env=clean_env(**env), capture_output=True, text=True, timeout=timeout
    )


def one_line(proc: subprocess.CompletedProcess, code: int, *words: str) -> str:
    """The failure's one line (the last; log lines of what went well may come before)."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stderr and "File " not in proc.stderr, proc.stderr
    failures = [line for line in lines if "cannot start: " in line]
    assert failures == lines[-1:], proc.stderr
    for word in words:
        assert word in failures[0], failures[0]
    return failures[0]


@pytest.fixture
def listening():
    """A port something listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def test_invalid_settings_are_one_line_naming_flag_and_variable(tmp_path):
    proc = start(tmp_path, "--api-port", "70000")
    one_line(proc, daemon.EXIT_USAGE, "api_port", "--api-port", "PITUNE_API_PORT")
    proc = start(tmp_path, PITUNE_ZENOH_CONNECT='["tcp/1.2.3.4:7447"')  # broken JSON
    one_line(proc, daemon.EXIT_USAGE, "zenoh_connect", "JSON")


def test_gateway_tokens_that_cannot_work_are_one_line_without_the_secret(tmp_path):
    """A gateway id that is none, and the admin token given to a gateway: accepted before
    (the one useless, the other an admin); now the settings' usage error, the secret in
    neither line."""
    secret = "TOPSECRET-0123456789abcdef"
    proc = start(tmp_path, PITUNE_API_GATEWAY_TOKENS=f'{{"gw 1": "{secret}"}}')
    line = one_line(proc, daemon.EXIT_USAGE, "PITUNE_API_GATEWAY_TOKENS", "'gw 1' is not")
    assert secret not in proc.stderr, line
    proc = start(tmp_path, PITUNE_API_TOKEN=secret,
                 PITUNE_API_GATEWAY_TOKENS=f'{{"gw-1": "{secret}"}}')  # fmt: skip
    line = one_line(proc, daemon.EXIT_USAGE, "the token of gateway 'gw-1' is the admin token")
    assert secret not in proc.stderr, line


def test_missing_weights_and_config_files(tmp_path):
    proc = start(tmp_path, "--agent-weights", str(tmp_path / "nope.pt"))
    one_line(proc, daemon.EXIT_NO_INPUT, "agent weights file not found", "--agent-weights")
    proc = start(tmp_path, "--config", str(tmp_path / "nope.toml"))
    one_line(proc, daemon.EXIT_NO_INPUT, "config file not found")
    proc = start(tmp_path, "--zenoh-config", str(tmp_path / "nope.json5"))
    one_line(proc, daemon.EXIT_NO_INPUT, "Zenoh config file not found")


def test_a_config_file_that_is_not_toml_is_a_usage_error(tmp_path):
    """A typo in the file (or a file that is not text) is status 2, which supervisors do
    not restart on, not 1: a restart would fail the same way for ever."""
    broken = tmp_path / "broken.toml"
    broken.write_text("api_port = \n")
    proc = start(tmp_path, "--config", str(broken))
    one_line(proc, daemon.EXIT_USAGE, str(broken), "not valid TOML", "line 1")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\n")
    proc = start(tmp_path, PITUNE_CONFIG=str(binary))
    one_line(proc, daemon.EXIT_USAGE, str(binary), "not valid TOML", "utf-8")
    assert not (tmp_path / "pitune.db").exists()  # nothing was opened


def test_retention_settings_that_would_fail_every_pass_are_refused(tmp_path):
    """An archive that cannot be appended to, or a row limit SQLite cannot hold, would fail
    every retention pass while the tuner runs, leaving the store unbounded."""
    for archive in (tmp_path / "nowhere" / "pruned.jsonl", tmp_path):
        proc = start(tmp_path, PITUNE_HISTORY_ARCHIVE=str(archive))
        one_line(proc, daemon.EXIT_CANT_CREATE, str(archive), "PITUNE_HISTORY_ARCHIVE")
    assert not (tmp_path / "pitune.db").exists()  # nothing was opened
    proc = start(tmp_path, "--db", str(tmp_path), PITUNE_HISTORY_ARCHIVE=str(tmp_path / "a.jsonl"))
    one_line(proc, daemon.EXIT_CANT_CREATE, "is a directory")  # checked after the archive
    assert not (tmp_path / "a.jsonl").exists()  # which leaves no file behind
    proc = start(tmp_path, PITUNE_HISTORY_MAX_ROWS_PER_LOOP=str(10**20))
    one_line(proc, daemon.EXIT_USAGE, "PITUNE_HISTORY_MAX_ROWS_PER_LOOP", "less than or equal")


def test_db_pointing_at_a_directory(tmp_path):
    proc = start(tmp_path, "--db", str(tmp_path))
    one_line(proc, daemon.EXIT_CANT_CREATE, "is a directory", "--db")


def test_api_port_in_use_fails_before_the_tuner_joins_the_bus(tmp_path, listening):
    proc = start(tmp_path, "--api-port", str(listening), "--log-level", "INFO")
    line = one_line(proc, daemon.EXIT_UNAVAILABLE, str(listening), "--api-port")
    assert "in use" in line
    assert not (tmp_path / "pitune.db").exists()  # nothing was opened


def test_zenoh_port_in_use_and_bad_listen_endpoint(tmp_path, listening):
    proc = start(tmp_path, "--listen", f"tcp/127.0.0.1:{listening}")
    line = one_line(proc, daemon.EXIT_UNAVAILABLE, "Zenoh", "--listen", "Address already in use")
    assert ".rs:" not in line  # no Rust source locations
    proc = start(tmp_path, "--listen", "tcp/not-an-address")
    one_line(proc, daemon.EXIT_USAGE, "Zenoh endpoint", "tcp/127.0.0.1:7447")
    proc = start(tmp_path, "--listen", "bogus")
    one_line(proc, daemon.EXIT_USAGE, "Zenoh endpoint")
    broken = tmp_path / "zenoh.json5"  # a syntax error: the file's to fix, not the network
    broken.write_text('{ mode: "peer", listen: { endpoints: [\n')
    proc = start(tmp_path, "--zenoh-config", str(broken))
    one_line(proc, daemon.EXIT_USAGE, "invalid Zenoh endpoint or config", "expected")


def test_a_second_tuner_on_the_same_store_refuses_to_start(tmp_path):
    first = TunerProcess(tmp_path / "pitune.db", "--agent-weights", "untrained",
                         "--instance-id", "first", log=tmp_path / "first.log")  # fmt: skip
    try:
        proc = first.start()
        second = start(tmp_path, "--instance-id", "second")
        line = one_line(second, daemon.EXIT_LOCKED, "another tuner owns the store")
        assert f"pid {proc.pid} instance first" in line
        assert proc.running
        proc.signal(signal.SIGKILL)  # the lock dies with the process: no stale lock
        again = TunerProcess(tmp_path / "pitune.db", "--agent-weights", "untrained",
                             "--instance-id", "second", log=tmp_path / "second.log")  # fmt: skip
        try:
            assert again.start().signal(signal.SIGINT) == 0  # Ctrl-C: a clean shutdown
        finally:
            again.stop()
    finally:
        first.stop()


def test_a_tuner_in_a_store_directory_takes_the_lock_beside_the_database(tmp_path):
    lock = daemon.StoreLock(tmp_path / "sub" / "x.db", "me")
    try:
        assert (tmp_path / "sub" / "x.db.lock").read_text().startswith("pid ")
        with pytest.raises(daemon.StartupError) as refused:
            daemon.StoreLock(tmp_path / "sub" / "x.db", "other")
        assert refused.value.code == daemon.EXIT_LOCKED and "instance me" in refused.value.message
    finally:
        lock.release()
    daemon.StoreLock(tmp_path / "sub" / "x.db", "other").release()  # free again


def test_a_second_tuner_on_the_same_key_prefix_refuses_to_start(tmp_path):
    """Two stores, one bus: the second tuner sees the first one's liveliness token on its
    prefix, waits out a lease (a tuner killed moments ago) and refuses; on its own prefix
    it starts."""
    first = TunerProcess(tmp_path / "a" / "pitune.db", "--agent-weights", "untrained",
                         "--instance-id", "first", log=tmp_path / "first.log")  # fmt: skip
    try:
        first.start()
        second = start(tmp_path, "--connect", first.zenoh, "--instance-id", "second")
        line = one_line(second, daemon.EXIT_LOCKED, "key prefix 'pitune'", "--prefix")
        assert "pitune/tuners/first" in line
        assert "waiting up to" in second.stderr  # it waited for the token to go first
        # the first, running, noticed the second's token come and go (its liveliness watch)
        log = first.log.read_text()
        assert "another tuner appeared on the bus with key prefix 'pitune': " \
            "pitune/tuners/second" in log  # fmt: skip
        wait_until(lambda: "the other tuner pitune/tuners/second left" in first.log.read_text(),
                   timeout=15.0, what="the second tuner's token gone")  # fmt: skip
        other = TunerProcess(tmp_path / "b" / "pitune.db", "--agent-weights", "untrained",
                             "--connect", first.zenoh, "--prefix", "site2/pitune",
                             log=tmp_path / "other.log")  # fmt: skip
        try:
            other.start()
        finally:
            other.stop()
    finally:
        first.stop()


def test_a_tuner_token_that_appears_later_shows_in_the_running_tuners_health(tmp_path):
    """A token on the prefix declared after the tuner started (a second tuner started in
    the same instant passes its own start-up check): warned in the log and in /healthz
    while it lives, gone with it."""
    first = TunerProcess(tmp_path / "pitune.db", "--agent-weights", "untrained",
                         "--instance-id", "first", log=tmp_path / "first.log")  # fmt: skip
    try:
        first.start()
        peer = open_peer([first.zenoh])
        try:
            with first.http() as api:
                assert api.get("/healthz").json() == {"status": "ok", "detail": ""}
                token = peer.liveliness().declare_token("pitune/tuners/late")
                health = wait_until(
                    lambda: (h := api.get("/healthz").json())["detail"] and h, what="warning"
                )
                assert health == {
                    "status": "ok",
                    "detail": "another tuner on this key prefix: pitune/tuners/late",
                }
                token.undeclare()
                wait_until(lambda: not api.get("/healthz").json()["detail"], what="token gone")
        finally:
            peer.close()
        log = first.log.read_text()
        assert "another tuner appeared on the bus with key prefix 'pitune'" in log
        assert "the other tuner pitune/tuners/late left the bus" in log
    finally:
        first.stop()


def test_a_cluster_lease_longer_than_the_zenoh_transport_lease_is_refused(tmp_path):
    """A member paused (SIGSTOP, a frozen VM) longer than its Zenoh transport lease (10 s
    by default) loses its liveliness token, and the others take its leases at three
    ticks, while, waking, it still counts its own lease valid: cluster_lease_s above the
    transport lease is refused, naming both ways out. At or below it, or with the Zenoh
    lease raised, start-up goes on (here to the store: no PostgreSQL listens)."""
    from service.daemon.leasecheck import lease_mismatch
    from service.daemon.settings import load_settings

    url = f"postgresql://pitune@127.0.0.1:{free_port()}/pitune"
    proc = start(tmp_path, "--db", url, PITUNE_CLUSTER_LEASE_S="30")
    one_line(proc, daemon.EXIT_USAGE, "cluster_lease_s (30 s) is longer than",
             "Zenoh transport lease (10 s, transport/link/tx/lease)",
             "PITUNE_CLUSTER_LEASE_S) to at most 10", "to at least 30000 (ms)")  # fmt: skip
    longer = tmp_path / "zenoh.json5"
    longer.write_text("{ transport: { link: { tx: { lease: 30000 } } } }")
    for extra, lease in [((), "10"), (("--zenoh-config", str(longer)), "30")]:
        proc = start(tmp_path, "--db", url, *extra, PITUNE_CLUSTER_LEASE_S=lease)
        one_line(proc, daemon.EXIT_CANT_CREATE, "PostgreSQL")
    # one tuner on SQLite has no cluster lease to keep
    assert lease_mismatch(load_settings(db_path=tmp_path / "x.db", cluster_lease_s=30)) is None


def test_a_start_with_the_store_s_epoch_a_day_ahead_is_refused(tmp_path):
    """A start whose clock is 2 days behind the stored epoch took the clock as a lower
    epoch, which every gateway dropped as stale; it is refused in one line (status 2)
    naming both remedies, and the stored epoch stays."""
    store = Store(tmp_path / "pitune.db")
    ahead = store.next_epoch(time.time() + 2 * 86400.0)
    store.close()
    proc = start(tmp_path)
    one_line(proc, daemon.EXIT_USAGE, f"stored epoch {ahead} is 48.0 h ahead", "NTP",
             "PITUNE_EPOCH_RESET=1")  # fmt: skip
    store = Store(tmp_path / "pitune.db")
    assert store.next_epoch(time.time(), "keep") == ahead + 1
    store.close()


def test_the_operator_s_epoch_reset_starts_again_from_the_clock(tmp_path, caplog):
    """PITUNE_EPOCH_RESET (after fixing a clock that was ahead): the tuner starts from
    its clock, with an ERROR naming the reset; unset it is refused as above."""
    store = Store(tmp_path / "pitune.db")
    ahead = store.next_epoch(time.time() + 3 * 86400.0)
    store.close()
    with pytest.raises(EpochAheadError):
        Tuner(tuner_settings(tmp_path)).start()
    before = time.time() * 1000
    with Tuner(tuner_settings(tmp_path, epoch_reset=True)) as tuner:
        assert before <= tuner.epoch < ahead - 2 * 86_400_000
    assert "EPOCH RESET (PITUNE_EPOCH_RESET)" in caplog.text
