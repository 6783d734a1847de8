"""Identities: every slave and every master (the add-on) has a key pair and a certificate, made
on first start and kept in a folder private to its user. Its ID is the SHA-256 of the
certificate (base32, 52 characters; the first 16, "ABCD-EFGH-JKLM-NPQR", are its short ID, as
a log, `--status`, the zeroconf record and the Slaves panel show it). All traffic is TLS 1.3
with a certificate on both sides (Python's ssl), and each side pins the other's ID after the
handshake (docs/protocol.md, "Identities and trust").

Why a "public issuer": Python's ssl before 3.13 cannot ask a TLS client for a certificate
without checking it against a certificate authority, and offers no callback to accept a
self-signed one. So every identity certificate is signed by one issuer whose private key is
*public* (derived from a fixed string below): chain verification then passes for any KD Trace
identity, so that TLS still makes each side prove it holds its certificate's private key
(TLS 1.3 CertificateVerify). The issuer proves nothing and is trusted for nothing: trust
comes only from the IDs each side pins (approved, allowed, paired, or proved with the farm
secret). Keys and certificates are made with `cryptography`; nothing here is home-made
cryptography.
"""
from __future__ import annotations

import base64
import datetime
import functools
import hashlib
import os
import pathlib
import re
import shutil
import ssl
import tempfile
import threading
import time

from ..private import private_folder, write_private_file

KEY_FILE = "identity-key.pem"
CERT_FILE = "identity-cert.pem"
ID_LENGTH = 52                   # base32 of SHA-256, unpadded
SHORT_ID_LENGTH = 16             # what people compare and type: 80 bits
ISSUER_SEED_TEXT = b"KD Trace public identity issuer, version 1 (not a secret, not a trust root)"
_ID_ALPHABET = "ABCDEFGHIJKLMNOPQRSTUVWXYZ234567"
_creating = threading.Lock()


class IdentityError(OSError):
    """An identity folder that cannot be used (not private, unreadable, damaged)."""


# ----------------------------------------------------------------------------- IDs

def id_of_certificate(der: bytes) -> str:
    """The full ID of a certificate (DER bytes): base32 of its SHA-256, 52 characters."""
    return base64.b32encode(hashlib.sha256(der).digest()).decode("ascii").rstrip("=")


def normalize_id(text: str) -> str:
    """An ID as typed or pasted: upper case, without dashes and spaces; 0, 1 and 8 read as O,
    I and B (base32 has no such digits)."""
    text = re.sub(r"[\s\-]", "", str(text)).upper()
    return text.translate(str.maketrans("018", "OIB"))


def check_id_pattern(text: str) -> str:
    """An ID (or the first 16 or more characters of one, such as a short ID) normalized; a
    ValueError names what is wrong."""
    pattern = normalize_id(text)
    if not SHORT_ID_LENGTH <= len(pattern) <= ID_LENGTH or any(c not in _ID_ALPHABET
                                                                   for c in pattern):
        raise ValueError(f"not a KD Trace ID: {str(text)[:80]!r} (16 to 52 characters of "
                         f"A-Z and 2-7, as a slave's log or the Slaves panel shows it)")
    return pattern


def id_matches(pattern: str, full_id: str) -> bool:
    """`full_id` is the ID `pattern` names: a full ID, or its first 16 or more characters."""
    try:
        pattern = check_id_pattern(pattern)
    except ValueError:
        return False
    return full_id.startswith(pattern)


def grouped(text: str) -> str:
    return "-".join(text[i:i + 4] for i in range(0, len(text), 4))


def short_id(full_id: str) -> str:
    """ABCD-EFGH-JKLM-NPQR: the first 80 bits, as people compare and type them."""
    return grouped(full_id[:SHORT_ID_LENGTH])


def peer_id(tls_socket: ssl.SSLSocket) -> str:
    """The ID of the certificate the peer proved in the TLS handshake."""
    der = tls_socket.getpeercert(binary_form=True)
    if not der:
        raise ssl.SSLError("the peer presented no certificate")
    return id_of_certificate(der)


# ----------------------------------------------------------------------------- the issuer

@functools.lru_cache(maxsize=1)
def _issuer():
    """(private key, certificate) of the public issuer: derived from a fixed string, the same
    on every machine. Ed25519 signatures are deterministic, so its certificate is too."""
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.x509.oid import NameOID
    key = Ed25519PrivateKey.from_private_bytes(hashlib.sha256(ISSUER_SEED_TEXT).digest())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "KD Trace public identity issuer")])
    certificate = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name)
        .public_key(key.public_key()).serial_number(1)
        .not_valid_before(datetime.datetime(2024, 1, 1, tzinfo=datetime.timezone.utc))
        .not_valid_after(datetime.datetime(9999, 12, 31, 23, 59, 59, tzinfo=datetime.timezone.utc))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                     key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, key_cert_sign=True, crl_sign=False,
                                     encipher_only=False, decipher_only=False), critical=True)
        .sign(key, None))
    return key, certificate


def issuer_pem() -> str:
    from cryptography.hazmat.primitives.serialization import Encoding
    return _issuer()[1].public_bytes(Encoding.PEM).decode("ascii")


def _new_identity_files(role: str) -> tuple[bytes, bytes]:
    """(key PEM, certificate PEM) of a new identity: an ECDSA P-256 key, its certificate
    signed by the public issuer, valid for TLS clients and servers, with no end date."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    issuer_key, issuer = _issuer()
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"KD Trace {role}")])
    certificate = (
        x509.CertificateBuilder().subject_name(subject).issuer_name(issuer.subject)
        .public_key(key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(datetime.datetime(2024, 1, 1, tzinfo=datetime.timezone.utc))
        .not_valid_after(datetime.datetime(9999, 12, 31, 23, 59, 59, tzinfo=datetime.timezone.utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                              ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .sign(issuer_key, None))
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    return key_pem, certificate.public_bytes(serialization.Encoding.PEM)


# ----------------------------------------------------------------------------- identities

def _create(folder: pathlib.Path, role: str, wait_s: float = 30.0) -> None:
    """Make the identity in `folder`. Several processes may try at once (local slaves sharing
    a folder): the one that creates the key file (O_EXCL) makes the identity, writing the
    certificate last (atomically); the others wait for the certificate."""
    try:
        fd = os.open(folder / KEY_FILE, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        deadline = time.monotonic() + wait_s
        while not (folder / CERT_FILE).exists():
            if time.monotonic() > deadline:
                raise IdentityError(f"{folder} holds a key but no certificate: another process "
                                    f"did not finish making the identity (remove the folder "
                                    f"to make a new one)") from None
            time.sleep(0.05)
        return
    key_pem, cert_pem = _new_identity_files(role)
    with os.fdopen(fd, "wb") as handle:
        handle.write(key_pem)
    write_private_file(folder / CERT_FILE, cert_pem)   # last: a certificate means a whole identity


class Identity:
    """A key pair and certificate on disk, and the TLS contexts that present them."""

    def __init__(self, folder, role: str = "peer"):
        self.folder = pathlib.Path(folder)
        self.role = role
        try:
            cert_pem = (self.folder / CERT_FILE).read_bytes()
            (self.folder / KEY_FILE).stat()
            der = ssl.PEM_cert_to_DER_cert(cert_pem.decode("ascii"))
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            raise IdentityError(f"cannot read the identity in {self.folder}: {exc}") from None
        self.id = id_of_certificate(der)
        self._contexts = {}
        self._lock = threading.Lock()

    @property
    def short_id(self) -> str:
        return short_id(self.id)

    @classmethod
    def load_or_create(cls, folder, role: str = "peer") -> "Identity":
        """The identity kept in `folder` (made private: 0700, this user's), made there on
        first use. Several processes may start at once with one folder (local slaves): one
        makes it, the others read it."""
        try:
            folder = private_folder(folder)
        except OSError as exc:
            raise IdentityError(f"identity folder {folder}: {exc}") from None
        with _creating:
            if not (folder / CERT_FILE).exists():
                _create(folder, role)
        return cls(folder, role)

    @classmethod
    def ephemeral(cls, role: str = "peer") -> "Identity":
        """A new identity for this process only (tests, benchmarks, a master without a
        folder): made in a private temporary folder, loaded into its TLS contexts at once,
        then the folder is removed."""
        folder = tempfile.mkdtemp(prefix="kdtrace-identity-")
        try:
            identity = cls.load_or_create(pathlib.Path(folder) / "id", role)
            identity.server_context()
            identity.client_context()
        finally:
            shutil.rmtree(folder, ignore_errors=True)
        return identity

    def _context(self, server_side: bool) -> ssl.SSLContext:
        with self._lock:
            context = self._contexts.get(server_side)
            if context is None:
                context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER if server_side
                                         else ssl.PROTOCOL_TLS_CLIENT)
                context.minimum_version = ssl.TLSVersion.TLSv1_3
                context.check_hostname = False     # peers are pinned by ID, not by name
                context.verify_mode = ssl.CERT_REQUIRED   # both sides present a certificate
                context.load_verify_locations(cadata=issuer_pem())
                try:
                    context.load_cert_chain(self.folder / CERT_FILE, self.folder / KEY_FILE)
                except (OSError, ssl.SSLError) as exc:
                    raise IdentityError(f"cannot load the identity in {self.folder}: {exc}") from None
                if server_side:
                    context.num_tickets = 0        # no session resumption: nothing to resume
                self._contexts[server_side] = context
            return context

    def server_context(self) -> ssl.SSLContext:
        return self._context(True)

    def client_context(self) -> ssl.SSLContext:
        return self._context(False)
