"""Bus encryption: Zenoh TLS links, both ends proving a certificate of the lab's authority (mTLS).

Credentials (:mod:`bridge.bus_credentials`) decide who may open a session, but the traffic itself
is plain TCP: anyone on the path between the PC and the board reads the states, and a machine in
the middle (ARP spoofing on a shared lab network) could inject into a session once it is open.
``XNECK_ZENOH_TLS`` names a folder made by ``xneck bus tls DIR --host <address> ...`` (on the PC):

``ca.pem``
    the lab's certificate authority; its key ``ca.key`` stays with whoever made the folder
    (:func:`load` does not need it: do not copy it to the board);
``node.pem`` and ``node.key``
    the certificate every machine of the stack presents, signed by that authority, naming the
    addresses peers connect to (``--host``: the board's and the PC's IP addresses or names), and
    its private key (mode 600).

A process with it may listen and connect on ``tls/<host>:<port>`` endpoints: the link is encrypted,
the listener proves it holds a certificate of the lab's authority for the address the peer
connected to, and the peer proves one too (Zenoh's ``enable_mtls``), so a peer without the folder,
or with another lab's, gets no link. Plain ``tcp/`` and Unix-socket endpoints keep working (within
a machine); a process that listens on a ``tcp/`` endpoint other machines reach while it has TLS
warns (bridge.session). Credentials still apply on top: TLS hides and protects the traffic,
credentials name the user (viewers, :mod:`bridge.bus_credentials`).

Validation needs the standard library only (the bridge's board has no ``cryptography``); making a
folder (:func:`write_new`) needs ``cryptography``, which the PC's install has.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import ssl
import time
from dataclasses import dataclass
from pathlib import Path

from bridge.small_file import read_checked

__all__ = ["ENV_TLS", "Tls", "TlsError", "from_env", "load", "write_new", "zenoh_tls"]

ENV_TLS = "XNECK_ZENOH_TLS"
CA, CERT, KEY, CA_KEY = "ca.pem", "node.pem", "node.key", "ca.key"
MAX_PEM_BYTES = 64 * 1024
DEFAULT_DAYS = 825  # the longest validity browsers still accept for a server certificate
WARN_DAYS = 30


class TlsError(ValueError):
    """A TLS folder that cannot be used, with the reason and the fix."""


@dataclass(frozen=True)
class Tls:
    """The TLS material of a folder: paths, the addresses the certificate names and its end (UTC)."""

    path: Path
    hosts: tuple[str, ...]
    not_after: dt.datetime

    @property
    def ca(self) -> Path:
        return self.path / CA

    @property
    def cert(self) -> Path:
        return self.path / CERT

    @property
    def key(self) -> Path:
        return self.path / KEY

    def days_left(self, now: float | None = None) -> float:
        return (self.not_after.timestamp() - (time.time() if now is None else now)) / 86400.0


def _pem(path: Path, marker: str, where: str, private: bool = False) -> None:
    text = read_checked(path, f"{where}: {path.name}", TlsError, kind="PEM file", max_bytes=MAX_PEM_BYTES,
                        private=private, hint=" (xneck bus tls DIR --host ... makes the folder)")
    if f"-----BEGIN {marker}" not in text and not (marker == "PRIVATE KEY" and "PRIVATE KEY-----" in text):
        raise TlsError(f"{where}: {path.name} holds no PEM {marker.lower()}")


def _decode(path: Path, where: str) -> dict:
    try:
        return ssl._ssl._test_decode_cert(str(path))  # type: ignore[attr-defined]  # stdlib: no cryptography on the board
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise TlsError(f"{where}: {path.name} is not a readable X.509 certificate: {exc}") from None


def load(path: str | os.PathLike[str], now: float | None = None) -> Tls:
    """The TLS folder ``path``, checked: ``ca.pem``, ``node.pem`` (not expired, not yet valid, with the
    addresses it names) and ``node.key`` (mode 600). Raises :class:`TlsError` naming the file."""
    p = Path(path).expanduser()
    where = f"{ENV_TLS} {p}"
    if not p.is_dir():
        raise TlsError(f"{where} is not a directory (xneck bus tls DIR --host ... makes one)")
    _pem(p / CA, "CERTIFICATE", where)
    _pem(p / CERT, "CERTIFICATE", where)
    _pem(p / KEY, "PRIVATE KEY", where, private=True)
    _decode(p / CA, where)
    cert = _decode(p / CERT, where)
    try:  # the standard library's check that the key is the certificate's (Zenoh only says KeyMismatch)
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(p / CERT, p / KEY)
    except ssl.SSLError as exc:
        raise TlsError(f"{where}: {KEY} is not the key of {CERT} ({exc.reason or exc}): copy both from the same "
                       "folder") from None
    now = time.time() if now is None else now
    begins, ends = ssl.cert_time_to_seconds(cert["notBefore"]), ssl.cert_time_to_seconds(cert["notAfter"])
    if now >= ends:
        raise TlsError(f"{where}: {CERT} expired on {cert['notAfter']}: make a new folder (xneck bus tls) and copy it "
                       "to every machine")
    if now < begins:
        raise TlsError(f"{where}: {CERT} is valid only from {cert['notBefore']}: is this machine's clock right?")
    hosts = tuple(value for kind, value in cert.get("subjectAltName", ()) if kind in ("DNS", "IP Address"))
    if not hosts:
        raise TlsError(f"{where}: {CERT} names no address (subjectAltName): peers could not verify it")
    return Tls(path=p, hosts=hosts, not_after=dt.datetime.fromtimestamp(ends, dt.UTC))


def from_env(environ: os._Environ[str] | dict[str, str] = os.environ) -> Tls | None:
    """The folder ``XNECK_ZENOH_TLS`` names, checked (None if unset or empty)."""
    path = environ.get(ENV_TLS, "").strip()
    return load(path) if path else None


def zenoh_tls(tls: Tls) -> dict:
    """Zenoh's ``transport/link/tls`` section: one certificate to listen and to connect, the lab's
    authority to verify the other end, both ends authenticated, and the address connected to checked
    against the certificate's names."""
    return {"root_ca_certificate": str(tls.ca), "listen_certificate": str(tls.cert),
            "listen_private_key": str(tls.key), "connect_certificate": str(tls.cert),
            "connect_private_key": str(tls.key), "enable_mtls": True, "verify_name_on_connect": True}


def write_new(path: str | os.PathLike[str], hosts: list[str], days: int = DEFAULT_DAYS) -> Tls:
    """A new TLS folder at ``path`` (created; an existing one is never replaced: FileExistsError):
    a lab authority (EC P-256, 10 years) and a certificate for ``hosts`` (IP addresses or DNS
    names) valid ``days``, for server and client use, keys mode 600. Needs ``cryptography``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not hosts:
        raise TlsError("name at least one address peers connect to (--host), e.g. the board's IP address")
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            if not h or any(c.isspace() or c in "/:" for c in h):
                raise TlsError(f"host {h!r} is neither an IP address nor a DNS name") from None
            names.append(x509.DNSName(h))
    if not 1 <= days <= 3650:
        raise TlsError(f"days must be 1-3650, got {days}")
    p = Path(path).expanduser()
    p.mkdir(mode=0o700)  # FileExistsError: never replaced
    now = dt.datetime.now(dt.UTC) - dt.timedelta(minutes=5)  # a peer's clock a little behind still accepts it
    ca_key, key = ec.generate_private_key(ec.SECP256R1()), ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"xneck lab authority {p.resolve().name}")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
          .serial_number(x509.random_serial_number()).not_valid_before(now)
          .not_valid_after(now + dt.timedelta(days=3650))
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                       data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                       crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    node = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "xneck bus")]))
            .issuer_name(ca_name).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))

    def write(name: str, data: bytes, mode: int) -> None:
        fd = os.open(p / name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)

    pkcs8 = serialization.PrivateFormat.PKCS8
    write(CA_KEY, ca_key.private_bytes(serialization.Encoding.PEM, pkcs8, serialization.NoEncryption()), 0o600)
    write(KEY, key.private_bytes(serialization.Encoding.PEM, pkcs8, serialization.NoEncryption()), 0o600)
    write(CA, ca.public_bytes(serialization.Encoding.PEM), 0o644)
    write(CERT, node.public_bytes(serialization.Encoding.PEM), 0o644)
    return load(p)
