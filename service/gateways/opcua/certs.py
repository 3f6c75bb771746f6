"""Self-signed OPC UA application certificates (``pitune gateway certs``).

An OPC UA application instance certificate carries the application URI as a URI
subject alternative name (servers check it against the session's ApplicationUri) and
the host name as a DNS name. The certificate is written DER (what OPC UA servers'
trust lists take), the key PEM (PKCS#8, unencrypted: protect the file, mode 0600).
The site's OPC UA administrator then puts the certificate in the server's trusted list.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

from asyncua.crypto import cert_gen
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID


def generate_pair(
    cert_file: Path,
    key_file: Path,
    *,
    application_uri: str = "urn:pitune:gateway",
    common_name: str = "pitune OPC UA gateway",
    hosts: list[str] | None = None,
    days: int = 365 * 2,
    server: bool = False,
    replace: bool = False,
) -> x509.Certificate:
    """Write a new key and a self-signed certificate for it; return the certificate.

    ``server``: a server certificate (the simulated DCS) instead of a client one.
    FileExistsError if either file exists, unless ``replace``: a site's pair is trusted
    by its server, and overwriting it locks the gateway out. The key is mode 0600 in
    either case (a replaced file keeps no mode of its own).
    """
    if days < 1:
        raise ValueError(f"days must be at least 1, not {days}")
    if not replace:
        taken = [str(f) for f in (cert_file, key_file) if f.exists()]
        if taken:
            raise FileExistsError(f"{', '.join(taken)} exists (--force replaces it)")
    hosts = hosts or [socket.gethostname()]
    key = cert_gen.generate_private_key()
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(application_uri)]
    names += [x509.DNSName(h) for h in hosts]
    use = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    cert = cert_gen.generate_self_signed_app_certificate(
        key, common_name, {"organizationName": "pitune"}, names, extended=[use], days=days
    )
    cert_file.parent.mkdir(parents=True, exist_ok=True)
    key_file.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        os.fchmod(fd, 0o600)  # O_CREAT's mode applies only to a file it creates
        out.write(cert_gen.dump_private_key_as_pem(key))
    cert_file.write_bytes(cert.public_bytes(Encoding.DER))
    return cert
