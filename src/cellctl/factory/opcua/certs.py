"""The OPC UA server's own certificate: self-signed, made at the first run, kept in
``<cell>/state/opcua/`` (the directory 0700, the key 0600).

::

    cert, key = ensure_certificate(Path("cell"), "urn:cellctl:host:cell", "127.0.0.1")

It is made again only when it has expired or no longer names the application URI or the
listen host; a client that trusted the old one must then trust the new one.
"""

from __future__ import annotations

import datetime
import hashlib
import ipaddress
import os
import socket
from pathlib import Path

from asyncua.crypto import cert_gen
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID

from cellctl.clock import REAL_CLOCK
from cellctl.errors import UsageError

CERT_DIR = Path("state") / "opcua"
CERT_FILE = "server-cert.der"
KEY_FILE = "server-key.pem"
#: Years a certificate is made for (a cell's server is not a public web site: clients trust
#: this one certificate by its thumbprint, and a new one would have to be trusted again).
VALID_DAYS = 5 * 365


def ensure_certificate(directory: Path, app_uri: str, host: str) -> tuple[Path, Path]:
    """The certificate (DER) and key (PEM) files of the cell's server, made if needed."""
    folder = directory / CERT_DIR
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.chmod(folder, 0o700)
        cert_path, key_path = folder / CERT_FILE, folder / KEY_FILE
        if key_path.exists():
            os.chmod(key_path, 0o600)
            key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        else:
            key = cert_gen.generate_private_key()
            _write(key_path, cert_gen.dump_private_key_as_pem(key), 0o600)
        if not _usable(cert_path, key, app_uri, host):
            names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(app_uri)]
            names += [x509.DNSName(n) for n in dict.fromkeys(["localhost", socket.gethostname()])]
            address = _address(host)
            if address is not None:
                names.append(x509.IPAddress(address))
            elif host not in ("localhost", socket.gethostname()):
                names.append(x509.DNSName(host))
            cert = cert_gen.generate_self_signed_app_certificate(
                key,  # type: ignore[arg-type]
                f"cellctl {directory.resolve().name}",
                {},
                names,
                extended=[ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
                days=VALID_DAYS,
            )
            _write(cert_path, cert.public_bytes(serialization.Encoding.DER), 0o644)
    except OSError as e:
        raise UsageError(f"{folder}: cannot keep the OPC UA certificate there: {e}") from None
    except ValueError as e:
        raise UsageError(f"{folder / KEY_FILE}: not a private key: {e}") from None
    return cert_path, key_path


def thumbprint(cert_path: Path) -> str:
    """The certificate's SHA-1 thumbprint, as OPC UA clients show it (hex, colon-separated)."""
    digest = hashlib.sha1(cert_path.read_bytes(), usedforsecurity=False).hexdigest().upper()
    return ":".join(digest[i : i + 2] for i in range(0, len(digest), 2))


def _usable(cert_path: Path, key: object, app_uri: str, host: str) -> bool:
    try:
        cert = x509.load_der_x509_certificate(cert_path.read_bytes())
    except (OSError, ValueError):
        return False
    # A certificate's validity is the real world's: the real clock's wall time, always.
    now = datetime.datetime.fromtimestamp(REAL_CLOCK.now(), datetime.UTC)
    if cert.not_valid_after_utc <= now + datetime.timedelta(1):
        return False
    public = getattr(key, "public_key", None)
    if public is None or public().public_numbers() != cert.public_key().public_numbers():  # type: ignore[union-attr]
        return False
    try:
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return False
    address = _address(host)
    if address is not None:
        named = address in names.get_values_for_type(x509.IPAddress)
    else:
        named = host in names.get_values_for_type(x509.DNSName)
    return named and app_uri in names.get_values_for_type(x509.UniformResourceIdentifier)


def _address(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return None


def _write(path: Path, data: bytes, mode: int) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, mode)
    os.replace(tmp, path)
