"""Who may talk to whom (docs/protocol.md, "Identities and trust").

A master sends scenes only to a slave whose ID the user approved (the Slaves panel, remembered
in the preferences), that the add-on started itself (local slaves), or that proves the farm
secret. A slave serves a master whose ID its owner allowed (`--allow`, kept in
`allowed-masters.txt` of its identity folder), that paired with the one-time pairing code the
slave shows, or that proves the farm secret. Every proof is an HMAC-SHA256 sent inside the TLS
channel and bound to both pinned IDs, so it is worth nothing on another connection, and the
master proves first: a slave answers an anonymous connection with nothing derived from a
secret. The farm secret is generated (256 random bits), never typed, so what a master's proof
gives a fake slave cannot be guessed offline either; a pairing code is short, so the master
sends its proof only to the slave whose ID the user picked, and the slave retires a code after
PAIRING_TRIES wrong ones.

A connection renders only scenes it uploaded or proved it holds: the holder proofs below are
HMACs under keys that only the scene's content gives (a digest that never travels, unlike the
scene's hash).
"""
from __future__ import annotations

import base64
import hashlib
import hmac
import os
import pathlib
import re
import secrets
import threading

from .identity import check_id_pattern, id_matches, short_id
from ..private import write_private_file

SECRET_ENV = "KDTRACE_SECRET"
FARM_SECRET_PREFIX = "kdtrace-farm-"
FARM_SECRET_RE = re.compile(r"kdtrace-farm-[a-z2-7]{52}")
NONCE_HEX = 64          # 32 random bytes
PROOF_HEX = 64          # SHA-256
PAIRING_CODE_LENGTH = 8          # base32 characters: 40 bits, against online guesses only
PAIRING_TRIES = 5                # wrong codes before a pairing code is retired
ALLOWED_MASTERS_FILE = "allowed-masters.txt"
MESH_PROOF_BYTES = 16


class AuthError(Exception):
    """A secret or allow list that cannot be used (unreadable, empty, typed by hand)."""


# ----------------------------------------------------------------------------- the farm secret

def new_farm_secret() -> str:
    """A farm secret: 256 random bits, as text (kdtrace-farm- and 52 base32 letters)."""
    return FARM_SECRET_PREFIX + base64.b32encode(secrets.token_bytes(32)).decode().rstrip("=").lower()


def check_farm_secret(value: bytes, where: str) -> bytes:
    if not FARM_SECRET_RE.fullmatch(value.decode("utf-8", "replace")):
        raise AuthError(f"{where} does not hold a generated farm secret: a password chosen by "
                        f"hand could be guessed offline by anyone who talks to a slave or "
                        f"master once. Make one with `kdtrace-slave --new-secret FILE` (or the "
                        f"add-on's New Farm Secret button) and give the same file to every "
                        f"machine of the farm")
    return value


def load_secret(secret_file: str | None = None, env: str = SECRET_ENV) -> bytes | None:
    """The farm secret: the file's contents (stripped) if a file is given, else the environment
    variable, else None. An empty or hand-made secret is an error, not 'no secret'."""
    if secret_file:
        try:
            with open(secret_file, "rb") as handle:
                data = handle.read(65536).strip()
        except OSError as exc:
            raise AuthError(f"cannot read secret file {secret_file}: {exc.strerror or exc}") from None
        if not data:
            raise AuthError(f"secret file {secret_file} is empty")
        return check_farm_secret(data, f"secret file {secret_file}")
    value = os.environ.get(env)
    if value is None:
        return None
    if not value.strip():
        raise AuthError(f"environment variable {env} is set but empty")
    return check_farm_secret(value.strip().encode("utf-8"), f"environment variable {env}")


def write_new_secret(path) -> str:
    """Write a new farm secret to `path` (0600); refuses to replace an existing file."""
    path = pathlib.Path(path)
    if path.exists():
        raise AuthError(f"{path} exists already: a farm secret is never overwritten (remove it "
                        f"first if you mean to replace the farm's secret)")
    secret = new_farm_secret()
    write_private_file(path, (secret + "\n").encode())
    return secret


# ----------------------------------------------------------------------------- proofs

def new_nonce() -> str:
    return secrets.token_hex(NONCE_HEX // 2)


def _mac(key: bytes, *parts: str) -> str:
    return hmac.new(key, "|".join(parts).encode(), hashlib.sha256).hexdigest()


def master_farm_proof(secret: bytes, master_nonce: str, master_id: str, slave_id: str) -> str:
    """What a master sends in HELLO: it holds the farm secret, on this connection between
    these two identities."""
    return _mac(secret, "kdtrace-farm", "master", master_nonce, master_id, slave_id)


def slave_farm_proof(secret: bytes, master_nonce: str, slave_nonce: str, master_id: str,
                     slave_id: str) -> str:
    """What a slave sends in WELCOME, only after the master's proof was right."""
    return _mac(secret, "kdtrace-farm", "slave", master_nonce, slave_nonce, master_id, slave_id)


def pairing_proof(code: str, master_nonce: str, master_id: str, slave_id: str) -> str:
    return _mac(normalize_code(code).encode(), "kdtrace-pair", "master", master_nonce,
                master_id, slave_id)


def proof_ok(expected: str, proof) -> bool:
    return isinstance(proof, str) and len(proof) == PROOF_HEX and hmac.compare_digest(expected, proof)


# ----------------------------------------------------------------------------- pairing codes

def new_pairing_code() -> str:
    code = base64.b32encode(secrets.token_bytes(5)).decode()[:PAIRING_CODE_LENGTH]
    return f"{code[:4]}-{code[4:]}"


def normalize_code(code: str) -> str:
    return re.sub(r"[\s\-]", "", str(code)).upper().translate(str.maketrans("018", "OIB"))


class PairingCode:
    """A slave's one-time pairing code: good for one master, retired after PAIRING_TRIES
    wrong proofs (so it can be guessed online only, PAIRING_TRIES times)."""

    def __init__(self, code: str | None = None):
        self.code = code or new_pairing_code()
        self.failures = 0
        self.used = False
        self._lock = threading.Lock()

    @property
    def active(self) -> bool:
        return not self.used and self.failures < PAIRING_TRIES

    def check(self, proof, master_nonce: str, master_id: str, slave_id: str) -> bool:
        """True (once) if `proof` is the code's; a wrong one counts against the code."""
        with self._lock:
            if not self.active:
                return False
            if proof_ok(pairing_proof(self.code, master_nonce, master_id, slave_id), proof):
                self.used = True
                return True
            self.failures += 1
            return False


# ----------------------------------------------------------------------------- allow lists

class AllowList:
    """IDs (or their first 16+ characters) allowed on this side, optionally kept in a file,
    one a line (# comments)."""

    def __init__(self, patterns=(), path=None):
        self.path = pathlib.Path(path) if path else None
        self._patterns: list = []
        self._lock = threading.Lock()
        if self.path is not None and self.path.exists():
            try:
                lines = self.path.read_text(encoding="utf-8").splitlines()
            except OSError as exc:
                raise AuthError(f"cannot read {self.path}: {exc.strerror or exc}") from None
            for number, line in enumerate(lines, 1):
                line = line.split("#", 1)[0].strip()
                if line:
                    try:
                        self._patterns.append(check_id_pattern(line))
                    except ValueError as exc:
                        raise AuthError(f"{self.path}, line {number}: {exc}") from None
        for pattern in patterns:
            self._patterns.append(check_id_pattern(pattern))

    def __len__(self) -> int:
        return len(self._patterns)

    def allows(self, full_id: str) -> bool:
        with self._lock:
            return any(id_matches(p, full_id) for p in self._patterns)

    def add(self, full_id: str, note: str = "") -> bool:
        """Allow `full_id` from now on (and in the file, if any); False if it was already."""
        pattern = check_id_pattern(full_id)
        with self._lock:
            if any(id_matches(p, pattern) for p in self._patterns):
                return False
            self._patterns.append(pattern)
            if self.path is not None:
                text = self.path.read_text(encoding="utf-8") if self.path.exists() else \
                    "# Masters this slave serves, one ID a line (kdtrace-slave --allow ID)\n"
                line = pattern + (f"  # {sanitize(note, 80)}" if note else "")
                write_private_file(self.path, (text + line + "\n").encode("utf-8"))
        return True

    def patterns(self) -> list:
        with self._lock:
            return list(self._patterns)


# ----------------------------------------------------------------------------- holding a scene
#
# A scene's hash travels (queries, frames, logs) and is shown; the digest of its geometry
# (Geometry.content_hash) never does, only hashes of it. A key made from that digest and the
# public hash proves that a master holds the content itself.

def _holder_key(private_digest: str, what: str, public_hash: str) -> bytes:
    return hashlib.blake2b(f"kdtrace-holder|{what}|{public_hash}".encode(),
                           key=private_digest.encode()[:64], digest_size=32).digest()


def holder_proof(private_digest: str, what: str, public_hash: str, nonce: str) -> str:
    """HMAC under the content's key of this connection's slave nonce. `what`: "scene" (the
    scene's hash) or "meshes" (its meshes_hash); `private_digest`: the geometry's content
    hash."""
    return hmac.new(_holder_key(private_digest, what, public_hash), nonce.encode(),
                    hashlib.sha256).hexdigest()


def mesh_holder_proof(private_digest: str, mesh_hash: bytes, nonce: str) -> bytes:
    """The same for one mesh (SCENE_MESHES: a mesh the slave takes from its cache), 16 bytes."""
    return hmac.new(_holder_key(private_digest, "mesh", mesh_hash.hex()), nonce.encode(),
                    hashlib.sha256).digest()[:MESH_PROOF_BYTES]


def mesh_proof_ok(private_digest: str, mesh_hash: bytes, nonce: str, proof: bytes) -> bool:
    return hmac.compare_digest(mesh_holder_proof(private_digest, mesh_hash, nonce), proof)


def scene_proofs(scene, nonce: str) -> dict:
    """SCENE_QUERY's holder proofs of `scene` for the slave nonce of this connection."""
    digest = scene.geometry.content_hash()
    fields = {"holds": holder_proof(digest, "scene", scene.hash, nonce)}
    if scene.meshes_hash is not None:
        fields["meshes_holds"] = holder_proof(digest, "meshes", scene.meshes_hash, nonce)
    return fields


# ----------------------------------------------------------------------------- names

def sanitize(text, limit: int = 64) -> str:
    """A peer's name for a log line or the panel: printable ASCII only (no newline can forge a
    log line, no escape sequence reaches a terminal), at most `limit` characters."""
    text = str(text)[:limit]
    return "".join(c if " " <= c <= "~" else "?" for c in text)


__all__ = ["AuthError", "AllowList", "PairingCode", "SECRET_ENV", "load_secret", "new_farm_secret",
           "write_new_secret", "master_farm_proof", "slave_farm_proof", "pairing_proof",
           "proof_ok", "new_nonce", "holder_proof", "mesh_holder_proof", "scene_proofs",
           "sanitize", "short_id"]
