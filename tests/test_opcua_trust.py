"""Client certificates checked against the trust list (``opcua.trusted_clients``), with asyncua's client over
Basic256Sha256 SignAndEncrypt on localhost and certificates made here: a self-signed one in the folder, one signed
by a CA whose certificate is in the folder, one trusted by nobody, and one copied in while the server runs."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto import cert_gen
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID
from fastapi.testclient import TestClient

from api.app import create_app
from api.opcua.passwords import hash_password
from autotuner.service.config import ConfigError, DaemonConfig, load_config
from helpers import free_port
from opcua_client import client, run, value

OPERATOR, VIEWER_PASSWORD = "trust-operator", "trust-viewer"
ENCRYPTED = "Basic256Sha256,SignAndEncrypt"


def _write(folder: Path, name: str, key: Any, cert: x509.Certificate) -> tuple[Path, Path]:
    """``name``-cert.der and ``name``-key.pem in ``folder``."""
    cert_path, key_path = folder / f"{name}-cert.der", folder / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(Encoding.DER))
    key_path.write_bytes(cert_gen.dump_private_key_as_pem(key))
    return cert_path, key_path


def self_signed(folder: Path, name: str) -> tuple[Path, Path]:
    """A self-signed client application certificate (application URI ``urn:test:NAME``) and its key."""
    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key, name, {}, [x509.UniformResourceIdentifier(f"urn:test:{name}"), x509.DNSName("localhost")],
        [ExtendedKeyUsageOID.CLIENT_AUTH])
    return _write(folder, name, key, cert)


def signed_by_ca(folder: Path, name: str) -> tuple[Path, Path, Path]:
    """A client certificate signed by a new CA: (the CA's certificate, the client's certificate, its key)."""
    ca_key = cert_gen.generate_private_key()
    ca = cert_gen.generate_self_signed_app_certificate(ca_key, f"{name} CA", {}, [], [])  # no usage: a CA
    key = cert_gen.generate_private_key()
    csr = cert_gen.generate_app_certificate_signing_request(
        key, name, {}, [x509.UniformResourceIdentifier(f"urn:test:{name}")], [ExtendedKeyUsageOID.CLIENT_AUTH])
    ca_path = folder / f"{name}-ca.der"
    ca_path.write_bytes(ca.public_bytes(Encoding.DER))
    return (ca_path, *_write(folder, name, key, cert_gen.sign_certificate_request(csr, ca, ca_key)))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A daemon with OPC UA (SignAndEncrypt only) trusting ``trusted/``: (endpoint, the server's certificate,
    the folder of client certificates made for the tests, the trusted folder)."""
    tmp = tmp_path_factory.mktemp("opcua-trust")
    certs, trusted = tmp / "clients", tmp / "trusted"
    certs.mkdir()
    trusted.mkdir()
    shutil.copy(self_signed(certs, "scada")[0], trusted)
    ca, _, _ = signed_by_ca(certs, "hmi")
    shutil.copy(ca, trusted)  # the CA only, not the certificate it signed
    self_signed(certs, "stranger")
    self_signed(certs, "late")
    config = DaemonConfig.model_validate({
        "history": str(tmp / "history.sqlite"),
        "opcua": {"port": free_port(), "security": ["Basic256Sha256_SignAndEncrypt"], "trusted_clients": str(trusted),
                  "users": [{"name": "viewer", "role": "viewer", "password_hash": hash_password(VIEWER_PASSWORD)}]},
        "loops": [{"id": "TIC-1", "sim": {"plant": "exp(-0.5*s)/(s+1)"}, "ts": 0.1, "speed": 2.0,
                   "monitor_period": 0.2, "tuning": {"amp": 5.0}, "limits": {"pv": [0.0, 100.0],
                                                                             "mv": [0.0, 100.0]}}]})
    app = create_app(config, env_token=OPERATOR)
    with TestClient(app, raise_server_exceptions=False):
        yield app.state.opcua_url, tmp / "opcua-server-cert.der", certs, trusted


async def encrypted(url: str, server_cert: Path, certs: Path, name: str) -> Client:
    """A viewer's client over SignAndEncrypt with the certificate ``name`` of ``certs`` (its application URI)."""
    c = client(url, "viewer", VIEWER_PASSWORD)
    c.application_uri = f"urn:test:{name}"
    await c.set_security_string(f"{ENCRYPTED},{certs / f'{name}-cert.der'},{certs / f'{name}-key.pem'},{server_cert}")
    return c


async def mode_over(c: Client) -> Any:
    async with c:
        assert c.security_policy.Mode == ua.MessageSecurityMode.SignAndEncrypt
        return await value(c, "TIC-1", "Mode")


def test_a_trusted_client_certificate_is_accepted_self_signed_or_by_its_ca(server):
    url, server_cert, certs, _ = server

    async def main() -> None:
        for name in ("scada", "hmi"):
            c = await encrypted(url, server_cert, certs, name)
            assert await mode_over(c) in ("AUTO", "MAN"), name

    run(main())


def test_an_untrusted_client_certificate_is_refused_until_it_is_copied_into_the_folder(server, caplog):
    url, server_cert, certs, trusted = server
    caplog.set_level(logging.INFO)

    async def main() -> None:
        for name in ("stranger", "late"):
            c = await encrypted(url, server_cert, certs, name)
            with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
                await mode_over(c)
        shutil.copy(certs / "late-cert.der", trusted)  # the administrator trusts it: no restart needed
        c = await encrypted(url, server_cert, certs, "late")
        assert await mode_over(c) in ("AUTO", "MAN")

    run(main())
    refusals = [r.getMessage() for r in caplog.records if r.name == "autotuner.api.opcua" and " refused" in r.message]
    assert len(refusals) == 2 and all("BadCertificateUntrusted" in m and "SHA-1 " in m for m in refusals), refusals
    assert "CN=stranger, URI=urn:test:stranger" in refusals[0] and "CN=late" in refusals[1]
    server_side = [r for r in caplog.records if r.name.startswith(("asyncua.server", "asyncuagds"))]
    assert not [r for r in server_side if r.levelno >= logging.ERROR or r.exc_info], server_side


def test_a_channel_signed_by_an_untrusted_key_cannot_borrow_a_trusted_certificate(server):
    """The client opens the secure channel with its own untrusted certificate and names a trusted one (public,
    without its key) in CreateSession: the check of the channel's certificate at ActivateSession refuses it."""
    url, server_cert, certs, _ = server
    borrowed = (certs / "scada-cert.der").read_bytes()

    async def main() -> None:
        c = await encrypted(url, server_cert, certs, "stranger")
        c.application_uri = "urn:test:scada"  # as the borrowed certificate says
        real = c.uaclient.create_session

        async def create_session(params: ua.CreateSessionParameters) -> ua.CreateSessionResult:
            params.ClientCertificate = borrowed
            return await real(params)

        c.uaclient.create_session = create_session
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            await mode_over(c)

    run(main())


def test_trusted_clients_must_be_a_folder_and_excludes_the_none_policy(tmp_path):
    path = tmp_path / "daemon.yaml"
    loop = '[{"id": "L", "sim": {"plant": "1/(s+1)"}, "ts": 0.1}]'
    path.write_text(f'{{"opcua": {{"security": ["Basic256Sha256_SignAndEncrypt"], "trusted_clients": "nowhere"}}, '
                    f'"loops": {loop}}}')
    with pytest.raises(ConfigError, match=r"opcua\.trusted_clients: .*nowhere is not a directory"):
        load_config(path)
    (tmp_path / "trusted").mkdir()
    path.write_text(f'{{"opcua": {{"trusted_clients": "trusted"}}, "loops": {loop}}}')
    with pytest.raises(ConfigError, match="'trusted_clients' needs 'security' without None"):
        load_config(path)
    path.write_text(f'{{"opcua": {{"security": ["Basic256Sha256_Sign"], "trusted_clients": "trusted"}}, '
                    f'"loops": {loop}}}')
    assert load_config(path).opcua.trusted_clients == tmp_path / "trusted"


def test_the_none_policy_needs_an_encrypting_policy_for_the_passwords(tmp_path):
    path = tmp_path / "daemon.yaml"
    loop = '[{"id": "L", "sim": {"plant": "1/(s+1)"}, "ts": 0.1}]'
    for security in ('["None"]', '["None", "Basic256Sha256_Sign"]'):
        path.write_text(f'{{"opcua": {{"security": {security}}}, "loops": {loop}}}')
        with pytest.raises(ConfigError, match="passwords on the None endpoint would travel in clear"):
            load_config(path)
    path.write_text(f'{{"opcua": {{"security": ["None", "Basic256Sha256_SignAndEncrypt"]}}, "loops": {loop}}}')
    assert load_config(path).opcua.security == ["None", "Basic256Sha256_SignAndEncrypt"]
