"""``scara-certs``: a set whose certificates verify against its CA, for the names given,
with keys only their owner reads; nothing overwritten unless asked; bad names refused."""

from __future__ import annotations

import contextlib
import ipaddress
import ssl
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from protocol.certs import main, self_signed


def names_of(path: Path) -> set[str]:
    certificate = x509.load_pem_x509_certificate(path.read_bytes())
    alternative = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName)
    dns = alternative.value.get_values_for_type(x509.DNSName)
    ips = [str(address) for address in alternative.value.get_values_for_type(x509.IPAddress)]
    return {*dns, *ips}


def test_a_set_verifies_against_its_ca_for_the_names_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--out", str(tmp_path), "--name", "robot.lan", "--name", "192.0.2.10"]) == 0
    assert "--tls " + str(tmp_path) in capsys.readouterr().out
    assert names_of(tmp_path / "server.pem") == {
        "localhost", "127.0.0.1", "::1", "robot.lan", "192.0.2.10",
    }  # fmt: skip
    # the server's certificate as TLS checks it: chain, name and key usage
    context = ssl.create_default_context(cafile=tmp_path / "ca.pem")
    context.load_cert_chain(tmp_path / "client.pem", tmp_path / "client-key.pem")
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=tmp_path / "ca.pem")
    server.load_cert_chain(tmp_path / "server.pem", tmp_path / "server-key.pem")
    server.verify_mode = ssl.CERT_REQUIRED
    incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
    back_in, back_out = ssl.MemoryBIO(), ssl.MemoryBIO()
    client_side = context.wrap_bio(incoming, outgoing, server_hostname="robot.lan")
    server_side = server.wrap_bio(back_in, back_out, server_side=True)
    for _ in range(10):  # the handshake, by hand: no socket
        for side in (client_side, server_side):
            with contextlib.suppress(ssl.SSLWantReadError):
                side.do_handshake()
        back_in.write(outgoing.read())
        incoming.write(back_out.read())
    client_side.do_handshake()
    assert server_side.getpeercert() is not None  # the client's certificate, checked
    usages = {
        stem: x509.load_pem_x509_certificate((tmp_path / f"{stem}.pem").read_bytes())
        .extensions.get_extension_for_class(x509.ExtendedKeyUsage)
        .value
        for stem in ("server", "client")
    }
    assert list(usages["server"]) == [ExtendedKeyUsageOID.SERVER_AUTH]
    assert list(usages["client"]) == [ExtendedKeyUsageOID.CLIENT_AUTH]
    for key in ("ca-key.pem", "server-key.pem", "client-key.pem"):
        assert stat.S_IMODE((tmp_path / key).stat().st_mode) == 0o600, key


def test_a_set_is_not_overwritten_unless_forced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--out", str(tmp_path)]) == 0
    first = (tmp_path / "ca.pem").read_bytes()
    assert main(["--out", str(tmp_path)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (tmp_path / "ca.pem").read_bytes() == first
    assert main(["--out", str(tmp_path), "--force"]) == 0
    assert (tmp_path / "ca.pem").read_bytes() != first


@pytest.mark.parametrize("name", ["robot lan", "http://robot", "*.lan", ""])
def test_a_name_that_is_neither_a_host_nor_an_address_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    assert main(["--out", str(tmp_path), "--name", name]) == 2
    assert repr(name) in capsys.readouterr().err
    assert not (tmp_path / "ca.pem").exists()


def test_a_self_signed_certificate_names_its_address_and_signs_itself() -> None:
    certificate, key = self_signed("127.0.0.1")
    loaded = x509.load_pem_x509_certificate(certificate)
    alternative = loaded.extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert ipaddress.ip_address("127.0.0.1") in alternative.value.get_values_for_type(
        x509.IPAddress
    )
    assert b"PRIVATE KEY" in key and loaded.issuer == loaded.subject
