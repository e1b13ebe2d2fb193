"""``scara-certs``: a local certificate authority and the certificates a TLS set-up needs.

Remote operators reach the robot over TLS: the routers' ``tls/`` links (``scara-router
--tls-cert``), ``scara-gui --https-cert`` and every Zenoh client's ``--zenoh-tls-ca``. This
command makes one set, for a demo or a small site without a PKI of its own:

- ``ca.pem``, ``ca-key.pem``: the authority every side trusts (keep its key off the robot);
- ``server.pem``, ``server-key.pem``: the routers' and ``scara-gui``'s certificate, valid for
  localhost, 127.0.0.1, ::1 and every ``--name`` (the names and addresses clients use);
- ``client.pem``, ``client-key.pem``: a client's certificate, for a router that asks for one
  (mutual TLS, ``scara-router --tls-client-ca ca.pem``).

Keys are ECDSA P-256, written readable by their owner only. Nothing is overwritten unless
``--force``.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from protocol.cli import add_verbosity, configure_logging, number, quiet_on_closed_pipe
from protocol.zenoh_can.config import LOOPBACK_NAMES, Tls

DEFAULT_OUT = Path("certs")
CA, SERVER, CLIENT = "ca", "server", "client"
"""The stems of the files written: ``NAME.pem`` and ``NAME-key.pem``."""


@dataclass(frozen=True, slots=True)
class CertificateSet:
    """Where one set lies: ``folder/ca.pem``, ``folder/server.pem`` ... (:data:`CA`)."""

    folder: Path

    def certificate(self, stem: str) -> Path:
        return self.folder / f"{stem}.pem"

    def key(self, stem: str) -> Path:
        return self.folder / f"{stem}-key.pem"

    def tls(self, side: str, *, mutual: bool) -> Tls:
        """The set as a ``client``'s or a ``router``'s TLS files (:class:`Tls`); ``mutual``:
        the client shows its certificate, the router asks for one."""
        ca = self.certificate(CA)
        if side == "client":
            shown = (self.certificate(CLIENT), self.key(CLIENT)) if mutual else (None, None)
            return Tls(ca, *shown)
        return Tls(ca if mutual else None, self.certificate(SERVER), self.key(SERVER))

    def files(self) -> list[Path]:
        return [
            path
            for stem in (CA, SERVER, CLIENT)
            for path in (self.certificate(stem), self.key(stem))
        ]


def subject_names(names: Sequence[str]) -> list[x509.GeneralName]:
    """An address as an IP entry, anything else as a DNS name (``ValueError`` if neither)."""
    entries: list[x509.GeneralName] = []
    for name in dict.fromkeys([*LOOPBACK_NAMES, *names]):  # in order, once each
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(name.strip("[]"))))
        except ValueError:
            if not name or any(c.isspace() or c in "/:*" for c in name):
                raise ValueError(f"--name {name!r} is not a host name or an address") from None
            entries.append(x509.DNSName(name))
    return entries


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _builder(
    subject: str, issuer: x509.Name, key: ec.EllipticCurvePrivateKey, days: int
) -> x509.CertificateBuilder:
    now = datetime.datetime.now(datetime.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(_name(subject))
        .issuer_name(issuer)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))  # a clock a little behind
        .not_valid_after(now + datetime.timedelta(days=days))
    )


def make_set(names: Sequence[str], days: int) -> dict[str, tuple[x509.Certificate, bytes]]:
    """The CA, the server's and a client's certificate, each with its key (PKCS#8 PEM)."""
    ca_key = _key()
    ca_name = _name("scara local CA")
    ca = (
        _builder("scara local CA", ca_name, ca_key, days)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )
    made = {CA: (ca, _pem(ca_key))}
    leaves: dict[str, tuple[str, list[x509.GeneralName], x509.ObjectIdentifier]] = {
        SERVER: ("scara server", subject_names(names), ExtendedKeyUsageOID.SERVER_AUTH),
        CLIENT: ("scara client", [x509.DNSName("scara-client")], ExtendedKeyUsageOID.CLIENT_AUTH),
    }
    for stem, (common_name, alternatives, usage) in leaves.items():
        key = _key()
        certificate = (
            _builder(common_name, ca_name, key, days)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(alternatives), critical=False)
            .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
            )
            .sign(ca_key, hashes.SHA256())
        )
        made[stem] = (certificate, _pem(key))
    return made


def self_signed(address: str, days: int = 30) -> tuple[bytes, bytes]:
    """A server certificate for ``address`` signed by its own key, and the key (PEM): for a
    server only one client, which pins this certificate, may open (no browser trusts it)."""
    key = _key()
    name = _name(address)
    certificate = (
        _builder(address, name, key, days)
        .add_extension(x509.SubjectAlternativeName(subject_names([address])), critical=False)
        .sign(key, hashes.SHA256())
    )
    return certificate.public_bytes(serialization.Encoding.PEM), _pem(key)


def _pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def write_set(where: CertificateSet, made: dict[str, tuple[x509.Certificate, bytes]]) -> None:
    """Certificates readable by all, keys by their owner only (created so, never widened)."""
    where.folder.mkdir(parents=True, exist_ok=True)
    for stem, (certificate, key) in made.items():
        where.certificate(stem).write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
        path = where.key(stem)
        path.unlink(missing_ok=True)
        descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(descriptor, "wb") as file:
            file.write(key)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-certs",
        description="Make a local CA and the certificates TLS needs: the routers' and "
        "scara-gui's (server.pem), a client's for mutual TLS (client.pem).",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=DEFAULT_OUT,
        help="folder to write them into (default %(default)s)",
    )
    parser.add_argument(
        "--name",
        action="append",
        default=[],
        metavar="HOST",
        help="a name or address clients reach the robot by, beside localhost, 127.0.0.1 and "
        "::1 (repeatable), e.g. --name robot.lan --name 192.168.1.20",
    )
    parser.add_argument(
        "--days",
        type=number(1, 3650, integer=True),
        default=365,
        help="how long the certificates are valid (default %(default)s)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite a set already there")
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    where = CertificateSet(args.out)
    there = [path for path in where.files() if path.exists()]
    if there and not args.force:
        print(f"scara-certs: {there[0]} exists: --force to make a new set", file=sys.stderr)
        return 2
    try:
        made = make_set(args.name, int(args.days))
        write_set(where, made)
    except (ValueError, OSError) as error:
        print(f"scara-certs: {error}", file=sys.stderr)
        return 2
    names = ", ".join(dict.fromkeys([*LOOPBACK_NAMES, *args.name]))
    server, server_key, ca = where.certificate(SERVER), where.key(SERVER), where.certificate(CA)
    print(f"scara-certs: wrote {where.folder}/: ca.pem, server.pem (for {names}), client.pem")
    print(f"  a router:  scara-router --tls-cert {server} --tls-key {server_key}")
    print(f"  a client:  --zenoh-tls-ca {ca}")
    print(f"  scara-gui: --https-cert {server} --https-key {server_key}")
    print(f"  scara-run: --tls {where.folder}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
