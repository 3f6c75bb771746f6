"""OPC UA security as a site requires it: Basic256Sha256 Sign & Encrypt with a client
certificate from files (made by ``pitune gateway certs``), a user with a password from
the environment; an untrusted certificate, a wrong password and security None are
refused by a server that trusts only the gateway's certificate."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import sys

import pytest
from asyncua import ua

from plant_sim.opcua_dcs import SERVER_URI, DcsSecurity, SimulatedDcs
from service.cli import main as pitune
from service.gateways.opcua.certs import generate_pair
from service.gateways.opcua.client import Item, OpcUaLink
from service.gateways.opcua.sitemap import parse_map
from service.procs import ROOT, clean_env
from service.wire.session import free_port
from tests.test_opcua_gateway import LOOP, tank

pytestmark = pytest.mark.timeout(120)
PASSWORD_ENV = "PITUNE_TEST_OPCUA_PASSWORD"


def test_encrypted_session_works_and_strangers_are_refused(tmp_path, monkeypatch):
    certs = tmp_path / "certs"
    # the command an integrator runs; the key file is private
    assert pitune(["gateway", "certs", "--out", str(certs), "--host", "localhost"]) == 0
    assert (certs / "gateway-key.pem").stat().st_mode & 0o077 == 0
    generate_pair(certs / "intruder-cert.der", certs / "intruder-key.pem", hosts=["localhost"])
    generate_pair(certs / "dcs-cert.der", certs / "dcs-key.pem", application_uri=SERVER_URI,
                  hosts=["localhost"], server=True)  # fmt: skip
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    (trusted / "gateway-cert.der").write_bytes((certs / "gateway-cert.der").read_bytes())
    monkeypatch.setenv(PASSWORD_ENV, "s3cret")
    security = DcsSecurity(
        certificate=certs / "dcs-cert.der", private_key=certs / "dcs-key.pem",
        trusted=[trusted], users={"pitune": "s3cret"}, allow_anonymous=False,
    )  # fmt: skip

    async def scenario() -> None:
        async with SimulatedDcs([tank()], port=free_port(), security=security) as dcs:
            base = dcs.site_map(certificate="gateway-cert.der", private_key="gateway-key.pem",
                                server_certificate="dcs-cert.der", user="pitune",
                                password_env=PASSWORD_ENV)  # fmt: skip

            def server(**change):
                data = {**base, "server": {**base["server"], **change}}
                return parse_map(data, base=certs).server

            async def connect(srv) -> list:
                link = OpcUaLink(srv)
                nodes = [(Item(0, "pv"), dcs.blocks[LOOP].node("PV"))]
                try:
                    changes = await link.open(nodes, sampling_ms={0: 100.0}, queue_size={0: 1},
                                              publishing_ms=100.0)  # fmt: skip
                    policy = link.client.security_policy
                    return [changes, policy.URI, policy.Mode]
                finally:
                    await link.close()

            changes, uri, mode = await connect(server())
            assert uri.endswith("#Basic256Sha256")
            assert mode == ua.MessageSecurityMode.SignAndEncrypt
            assert changes[0].good and changes[0].value == dcs.loops[0].settings.sp_low

            monkeypatch.setenv("PITUNE_TEST_NO_SUCH_VAR", "guess")
            refused = {
                "BadCertificateUntrusted": server(certificate="intruder-cert.der",
                                                  private_key="intruder-key.pem"),
                "BadUserAccessDenied": server(password_env="PITUNE_TEST_NO_SUCH_VAR"),
                "No matching endpoints": server(security="None", allow_insecure=True,
                                                allow_plaintext_password=True),
            }  # fmt: skip
            for reason, srv in refused.items():
                with pytest.raises(Exception, match=reason):  # asyncua raises several kinds
                    await connect(srv)
            # a server other than the pinned one (pinned here to another certificate) cannot
            # read what the gateway encrypts for the pinned one: no session, no password
            with pytest.raises(TimeoutError):
                await connect(server(server_certificate="intruder-cert.der"))

    asyncio.run(scenario())


def test_certs_never_replace_a_pair_unasked_and_the_key_is_private(tmp_path, capsys):
    out = ["gateway", "certs", "--out", str(tmp_path), "--host", "localhost"]
    assert pitune(out) == 0
    key = tmp_path / "gateway-key.pem"
    first = key.read_bytes()
    assert pitune(out) == 2  # the server trusts this pair: not replaced without --force
    assert "exists (--force replaces it)" in capsys.readouterr().err
    assert key.read_bytes() == first
    key.chmod(0o644)  # e.g. copied around with a umask that left it readable
    assert pitune([*out, "--force"]) == 0
    assert key.read_bytes() != first and key.stat().st_mode & 0o777 == 0o600
    with pytest.raises(SystemExit) as exit_:  # expired on arrival
        pitune([*out, "--force", "--days", "0"])
    assert exit_.value.code == 2


def test_a_password_in_clear_text_needs_an_explicit_opt_in(tmp_path, monkeypatch):
    """Security None with a user: asyncua sends the password as it is (a server offering
    security None, here the simulated DCS, names no encryption for it), readable by anyone
    on the path, as a relay between the gateway and the server records. The gateway
    refuses that map at start-up, one line, unless allow_plaintext_password = true."""
    import tomli_w

    monkeypatch.setenv(PASSWORD_ENV, PLAIN)
    security = DcsSecurity(allow_insecure=True, users={"pitune": PLAIN}, allow_anonymous=False)

    async def scenario() -> tuple[dict, bytes]:
        async with SimulatedDcs([tank()], port=free_port(), security=security) as dcs:
            site = dcs.site_map(security="None", allow_insecure=True, user="pitune",
                                password_env=PASSWORD_ENV)  # fmt: skip
            async with recording_relay(dcs.url) as (url, seen):
                opted = {**site["server"], "url": url, "allow_plaintext_password": True}
                link = OpcUaLink(parse_map({**site, "server": opted}).server)
                try:
                    nodes = [(Item(0, "pv"), dcs.blocks[LOOP].node("PV"))]
                    changes = await link.open(nodes, sampling_ms={0: 100.0}, queue_size={0: 1},
                                              publishing_ms=100.0)  # fmt: skip
                    assert changes[0].good
                finally:
                    await link.close()
            return site, bytes(seen)

    site, seen = asyncio.run(scenario())
    assert PLAIN.encode() in seen, "what allow_plaintext_password accepts"
    refused = tmp_path / "site.toml"
    refused.write_text(tomli_w.dumps(site))
    argv = [sys.executable, "-m", "service.cli", "gateway", "opcua", "--map", str(refused)]
    proc = subprocess.run(argv, cwd=ROOT, env=clean_env(**{PASSWORD_ENV: PLAIN}),
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "security \"None\" with user 'pitune' sends its password in clear text" in proc.stderr
    assert "allow_plaintext_password = true" in proc.stderr and PLAIN not in proc.stderr


PLAIN = "clear-text-marker-7f3a9c"


@contextlib.asynccontextmanager
async def recording_relay(url: str):
    """A loopback TCP relay to the server at ``url``: yields its own URL and the bytes
    the client sent through it."""
    host, port = url.split("//")[1].split("/")[0].rsplit(":", 1)
    seen = bytearray()

    async def pipe(reader, writer, record: bool) -> None:
        while data := await reader.read(65536):
            if record:
                seen.extend(data)
            writer.write(data)
            await writer.drain()
        writer.close()

    async def relay(reader, writer) -> None:
        up_reader, up_writer = await asyncio.open_connection(host, int(port))
        await asyncio.gather(pipe(reader, up_writer, True), pipe(up_reader, writer, False),
                             return_exceptions=True)  # fmt: skip

    server = await asyncio.start_server(relay, "127.0.0.1", 0)
    mine = server.sockets[0].getsockname()[1]
    try:
        yield url.replace(f":{port}/", f":{mine}/"), seen
    finally:
        server.close()
