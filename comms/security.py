"""Fleet security with Zenoh's own features: mutual TLS on every link and Zenoh access control.

    from comms.security import FleetKeys
    keys = FleetKeys.create("fleet-keys/", fleet="f1", drones=["drone_1", "drone_2"])   # CA + one cert each
    keys.check("drone_1")                     # SecurityError naming the file and the fix when unusable
    TransportConfig(security=SecurityConfig(keys_dir="fleet-keys/"), listen=["tls/127.0.0.1:0"], ...)

No home-made cryptography: certificates are made with ``cryptography`` (X.509, ECDSA P-256, SHA-256), the
TLS handshake, the certificate checks and the filtering are Zenoh's (``transport/link/tls`` with
``enable_mtls``, ``access_control`` with ``cert_common_names`` subjects). This module only writes the files
and the two Zenoh config sections.

The fleet folder (``skycap keys create``)
-----------------------------------------
``fleet.toml`` (the fleet id and every identity with its role), ``ca.pem`` (the fleet's certificate
authority), ``ca.key`` (the CA's private key: keep it on the operator's machine only; it is needed to add an
identity, not to fly), and per identity ``<id>.pem`` + ``<id>.key`` (private keys are written 0600 and never
overwritten). An identity is a certificate whose common name (CN) is the node id it publishes under
(``drone_1``, ``gcs``, ``sim``). A drone needs ``fleet.toml``, ``ca.pem`` and its own pair.

Who may do what (the ACL every node enforces on what it receives, and on what it sends)
-----------------------------------------------------------------------------------------
* Every identity may publish (put, liveliness token, queryable and its replies) only under its own
  ``skycap/v1/<fleet>/<id>/**``. Commands and plans live under ``gcs/``: only a ``gcs`` certificate can
  send them; a drone's certificate cannot command anyone; a message on another node's keys is dropped on
  receipt by every honest node (its ACL is checked against the certificate of the link it came on).
* Everyone in the fleet may subscribe and query.
* What a node sends to whom: ground stations get every topic except full-rate camera images
  (``camera/image`` stays on its drone: recorder and detector); a drone's teammates get state, health,
  detections, targets and formation plans; a peer holding the same certificate (the drone's camera service
  beside its agent) gets everything of that drone; ``router`` identities (a zenohd between links) get and
  relay everything and must enforce the same ACL themselves.
* The claimed ``header.sender_id`` of every message must equal the node segment of its key (checked by
  :class:`comms.transport.Transport` on receipt): with the ACL, that makes the sender id authenticated.

A node without a certificate of the fleet's CA cannot open a link at all (mutual TLS), so it can neither
receive nor send.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import logging
import os
import stat
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

from shared_msgs import keys as _keys
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["SecurityError", "SecurityConfig", "FleetKeys", "ROLES", "acl_config", "tls_config"]

ROLES = ("gcs", "drone", "sim", "router")
#: what a drone's session sends to its teammates (besides the ground station's and simulator's keys)
TEAM_TOPICS = (_keys.STATE, _keys.HEALTH, _keys.DETECTIONS, _keys.TARGET, _keys.FORMATION_PLAN, _keys.ALIVE)
_PUBLISH = ["put", "delete", "liveliness_token", "declare_queryable", "reply"]
_INTEREST = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
MANIFEST = "fleet.toml"


class SecurityError(SkycapError):
    """A missing, expired, foreign or badly protected key or certificate; the message names the file and the fix."""


@dataclass
class SecurityConfig:
    """``[transport.security]``: mutual TLS and access control from a fleet folder made by ``skycap keys``.

    ``keys_dir``: the fleet folder (``fleet.toml``, ``ca.pem``, ``<identity>.pem`` / ``.key``); empty = the
    transport is INSECURE (plaintext, anyone on the network can read and command: debugging only, logged
    loudly). ``identity``: the certificate this node presents (default: its node id, e.g. ``drone_1``).
    ``verify_name``: also check that the certificate of the peer a link connects to names the host it dialled
    (off by default: every certificate is checked against the fleet CA and the ACL binds each to its keys).
    """

    keys_dir: str = ""
    identity: str = ""
    verify_name: bool = False

    @property
    def enabled(self) -> bool:
        return bool(self.keys_dir)


def _utcnow() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def _write_private(path: Path, data: bytes) -> None:
    """Create ``path`` 0600; an existing file is never overwritten."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_new(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


@dataclass
class FleetKeys:
    """One fleet folder: its CA, its identities (id -> role) and their certificates."""

    folder: Path
    fleet: str
    identities: dict[str, str] = field(default_factory=dict)

    # ------------------------------------------------------------------ files
    @property
    def ca_cert_path(self) -> Path:
        return self.folder / "ca.pem"

    @property
    def ca_key_path(self) -> Path:
        return self.folder / "ca.key"

    def cert_path(self, identity: str) -> Path:
        return self.folder / f"{identity}.pem"

    def key_path(self, identity: str) -> Path:
        return self.folder / f"{identity}.key"

    # ------------------------------------------------------------------ create / load
    @classmethod
    def create(cls, folder: str | Path, fleet: str, drones: list[str] | tuple[str, ...] = (),
               gcs: list[str] | tuple[str, ...] = (_keys.GCS,), sim: bool = False, days: int = 365,
               hosts: list[str] | tuple[str, ...] = ()) -> FleetKeys:
        """A new fleet folder: the CA (valid 10 years) and a certificate per identity (``days``).

        ``hosts``: extra DNS names / IP addresses written into every certificate (for ``verify_name``).
        Refused if ``folder`` already holds a fleet (keys are never overwritten).
        """
        from cryptography.hazmat.primitives.asymmetric import ec

        folder = Path(folder)
        if (folder / MANIFEST).exists() or (folder / "ca.key").exists():
            raise SecurityError(f"{folder} already holds a fleet's keys; add an identity with `skycap keys add "
                                f"--keys {folder} ID --role drone`, or choose another folder")
        _keys._check(fleet, "fleet id")
        folder.mkdir(parents=True, exist_ok=True)
        os.chmod(folder, 0o700)
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca = _ca_certificate(ca_key, f"skycap fleet {fleet} CA", days=3650)
        _write_private(folder / "ca.key", _key_pem(ca_key))
        _write_new(folder / "ca.pem", _cert_pem(ca))
        keys = cls(folder, fleet, {})
        for ident, role in [(g, "gcs") for g in gcs] + [(d, "drone") for d in drones] + ([(_keys.SIM, "sim")] if sim else []):
            keys.add(ident, role, days=days, hosts=hosts)
        return keys

    @classmethod
    def load(cls, folder: str | Path) -> FleetKeys:
        folder = Path(folder)
        path = folder / MANIFEST
        if not path.is_file():
            raise SecurityError(f"{path} is missing: transport.security.keys_dir must be a fleet folder made by "
                                f"`skycap keys create --keys {folder} --fleet FLEET --drones drone_1,...`")
        try:
            doc = tomllib.loads(path.read_text())
            ids = {str(k): str(v["role"]) for k, v in doc.get("identities", {}).items()}
            fleet = str(doc["fleet"])
        except (tomllib.TOMLDecodeError, KeyError, TypeError, AttributeError) as e:
            raise SecurityError(f"{path} is not a fleet manifest ({e}); recreate it with `skycap keys create`") from None
        bad = {k: r for k, r in ids.items() if r not in ROLES}
        if bad:
            raise SecurityError(f"{path}: unknown role(s) {bad}; a role is one of {ROLES}")
        return cls(folder, fleet, ids)

    def _save_manifest(self) -> None:
        doc = {"fleet": self.fleet, "identities": {k: {"role": r} for k, r in sorted(self.identities.items())}}
        tmp = self.folder / (MANIFEST + ".tmp")
        tmp.write_text(tomli_w.dumps(doc))
        os.replace(tmp, self.folder / MANIFEST)

    def add(self, identity: str, role: str, days: int = 365, hosts: list[str] | tuple[str, ...] = ()) -> Path:
        """Issue a certificate for ``identity`` (its node id) with ``role``; returns the certificate's path."""
        from cryptography.hazmat.primitives.asymmetric import ec

        _keys._check(identity, "identity")
        if role not in ROLES:
            raise SecurityError(f"role {role!r} of {identity!r} is not one of {ROLES}")
        if identity in self.identities or self.cert_path(identity).exists() or self.key_path(identity).exists():
            raise SecurityError(f"{identity!r} already has a certificate in {self.folder}; identities are never "
                                f"re-issued in place: remove its files and its line in {MANIFEST} first")
        if not self.ca_key_path.is_file():
            raise SecurityError(f"{self.ca_key_path} is missing: adding an identity needs the CA's private key "
                                f"(kept on the operator's machine that ran `skycap keys create`)")
        ca_key = _load_key(self.ca_key_path)
        ca = _load_cert(self.ca_cert_path)
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _leaf_certificate(identity, key, ca, ca_key, days=days, hosts=hosts)
        _write_private(self.key_path(identity), _key_pem(key))
        _write_new(self.cert_path(identity), _cert_pem(cert))
        self.identities[identity] = role
        self._save_manifest()
        log.info("issued %s certificate %r (valid until %s) in %s", role, identity,
                 cert.not_valid_after_utc.date(), self.folder)
        return self.cert_path(identity)

    # ------------------------------------------------------------------ checks
    def check(self, identity: str, now: _dt.datetime | None = None) -> dict[str, Any]:
        """Raise :class:`SecurityError` unless ``identity`` can join: files present, key 0600, certificate
        signed by the fleet CA, not expired, matching its key, listed in the manifest. Returns its details."""
        now = now or _utcnow()
        if identity not in self.identities:
            raise SecurityError(f"identity {identity!r} is not in {self.folder / MANIFEST} (known: "
                                f"{sorted(self.identities)}); issue it with `skycap keys add --keys {self.folder} "
                                f"{identity} --role drone|gcs`")
        for p in (self.ca_cert_path, self.cert_path(identity), self.key_path(identity)):
            if not p.is_file():
                raise SecurityError(f"{p} is missing: copy it from the fleet folder made by `skycap keys create` "
                                    f"(a drone needs {MANIFEST}, ca.pem, {identity}.pem and {identity}.key)")
        mode = stat.S_IMODE(self.key_path(identity).stat().st_mode)
        if mode & 0o077:
            raise SecurityError(f"{self.key_path(identity)} is readable by others (mode {mode:o}): "
                                f"chmod 600 {self.key_path(identity)}")
        ca = _load_cert(self.ca_cert_path)
        cert = _load_cert(self.cert_path(identity))
        for what, c in (("the fleet CA", ca), (f"certificate {identity!r}", cert)):
            if now > c.not_valid_after_utc:
                raise SecurityError(f"{what} ({self.cert_path(identity) if c is cert else self.ca_cert_path}) "
                                    f"expired on {c.not_valid_after_utc:%Y-%m-%d %H:%M} UTC: issue a new one "
                                    f"(`skycap keys add`)")
            if now < c.not_valid_before_utc:
                raise SecurityError(f"{what} is not valid before {c.not_valid_before_utc:%Y-%m-%d %H:%M} UTC: "
                                    f"check this machine's clock ({now:%Y-%m-%d %H:%M} UTC)")
        try:
            cert.verify_directly_issued_by(ca)
        except Exception:
            raise SecurityError(f"{self.cert_path(identity)} is not signed by this fleet's CA "
                                f"({self.ca_cert_path}): it belongs to another fleet folder") from None
        from cryptography.hazmat.primitives import serialization
        pub = serialization.PublicFormat.SubjectPublicKeyInfo
        key = _load_key(self.key_path(identity))
        if key.public_key().public_bytes(serialization.Encoding.DER, pub) != cert.public_key().public_bytes(
                serialization.Encoding.DER, pub):
            raise SecurityError(f"{self.key_path(identity)} does not belong to {self.cert_path(identity)}")
        cn = _common_name(cert)
        if cn != identity:
            raise SecurityError(f"{self.cert_path(identity)} names {cn!r}, not {identity!r}")
        return {"identity": identity, "role": self.identities[identity], "fleet": self.fleet,
                "valid_until_utc": cert.not_valid_after_utc.isoformat(),
                "days_left": (cert.not_valid_after_utc - now).days}


def tls_config(keys: FleetKeys, identity: str, verify_name: bool = False) -> dict[str, Any]:
    """Zenoh's ``transport/link/tls`` section: this identity's pair for both directions, mutual TLS on."""
    cert, key = str(keys.cert_path(identity).resolve()), str(keys.key_path(identity).resolve())
    return {"root_ca_certificate": str(keys.ca_cert_path.resolve()), "listen_certificate": cert,
            "listen_private_key": key, "connect_certificate": cert, "connect_private_key": key,
            "enable_mtls": True, "verify_name_on_connect": bool(verify_name), "close_link_on_expiration": True}


def acl_config(keys: FleetKeys) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for this fleet (the same on every node; see the module doc)."""
    p = f"{_keys.PREFIX}/{keys.fleet}"
    common = [f"{p}/{_keys.GCS}/**", f"{p}/{_keys.SIM}/**"]
    to_gcs = [f"{p}/*/*", f"{p}/*/{_keys.CAMERA_THUMB}", f"{p}/*/{_keys.CAMERA_STATUS}", f"{p}/*/sim/**",
              f"{p}/*/formation/**"] + common
    to_team = [f"{p}/*/{t}" for t in TEAM_TOPICS] + common
    rules: list[dict] = [
        {"id": "interest", "messages": _INTEREST, "flows": ["ingress", "egress"], "permission": "allow",
         "key_exprs": [f"{p}/**"]},
        {"id": "send_to_gcs", "messages": _PUBLISH, "flows": ["egress"], "permission": "allow", "key_exprs": to_gcs},
        {"id": "send_to_team", "messages": _PUBLISH, "flows": ["egress"], "permission": "allow", "key_exprs": to_team},
        {"id": "relay", "messages": _PUBLISH, "flows": ["ingress", "egress"], "permission": "allow",
         "key_exprs": [f"{p}/**"]},
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    for ident, role in sorted(keys.identities.items()):
        sid = f"id_{ident}"
        subjects.append({"id": sid, "cert_common_names": [ident]})
        rules.append({"id": f"from_{ident}", "messages": _PUBLISH, "flows": ["ingress"], "permission": "allow",
                      "key_exprs": [f"{p}/{ident}/**"]})
        rules.append({"id": f"to_{ident}", "messages": _PUBLISH, "flows": ["egress"], "permission": "allow",
                      "key_exprs": [f"{p}/{ident}/**"]})
        own = {"gcs": ["send_to_gcs"], "drone": ["send_to_team"], "sim": ["send_to_team"], "router": ["relay"]}[role]
        policies.append({"id": f"p_{ident}", "subjects": [sid],
                         "rules": ["interest", f"from_{ident}", f"to_{ident}", *own]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


# ---------------------------------------------------------------------- X.509 helpers (cryptography)
def _key_pem(key) -> bytes:
    from cryptography.hazmat.primitives import serialization
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _cert_pem(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization
    return cert.public_bytes(serialization.Encoding.PEM)


def _load_key(path: Path):
    from cryptography.hazmat.primitives import serialization
    try:
        return serialization.load_pem_private_key(path.read_bytes(), password=None)
    except FileNotFoundError:
        raise SecurityError(f"{path} is missing") from None
    except ValueError as e:
        raise SecurityError(f"{path} is not a PEM private key ({e})") from None


def _load_cert(path: Path):
    from cryptography import x509
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except FileNotFoundError:
        raise SecurityError(f"{path} is missing: copy it from the fleet folder made by `skycap keys create`") from None
    except ValueError as e:
        raise SecurityError(f"{path} is not a PEM certificate ({e})") from None


def _common_name(cert) -> str:
    from cryptography.x509.oid import NameOID
    attrs = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(attrs[0].value) if attrs else ""


def _name(cn: str):
    from cryptography import x509
    from cryptography.x509.oid import NameOID
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "skycap"), x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _ca_certificate(key, cn: str, days: int):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    now = _utcnow()
    return (x509.CertificateBuilder().subject_name(_name(cn)).issuer_name(_name(cn)).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))


def _leaf_certificate(cn: str, key, ca, ca_key, days: int, hosts: list[str] | tuple[str, ...] = ()):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID
    now = _utcnow()
    sans: list = [x509.DNSName(cn), x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    return (x509.CertificateBuilder().subject_name(_name(cn)).issuer_name(ca.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
