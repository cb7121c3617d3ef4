"""The deploy router config (TLS, user/password, deny-by-default ACL) on loopback with throwaway certs."""

from __future__ import annotations

import datetime
import ipaddress
import json
import socket
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
x509 = pytest.importorskip("cryptography.x509", reason="needs the cryptography package for throwaway certs")
zenoh = pytest.importorskip("zenoh")

from cryptography.hazmat.primitives import hashes, serialization  # noqa: E402
from cryptography.hazmat.primitives.asymmetric import ec  # noqa: E402
from cryptography.x509.oid import NameOID  # noqa: E402

from service import Client, Service, ServiceConfig, ServiceError  # noqa: E402
from service.loadgen import CAMERA  # noqa: E402


def _cert(subject: str, key, issuer_name, issuer_key, ca: bool):
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .issuer_name(issuer_name or x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if not ca:
        names = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def _write(path: Path, obj) -> str:
    if hasattr(obj, "private_bytes"):
        data = obj.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    else:
        data = obj.public_bytes(serialization.Encoding.PEM)
    path.write_bytes(data)
    return str(path)


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    """Yields (endpoint, files): a router from deploy/router.json5 with a fake-engine service behind it."""
    tmp = tmp_path_factory.mktemp("tls")
    ca_key, key = ec.generate_private_key(ec.SECP256R1()), ec.generate_private_key(ec.SECP256R1())
    ca = _cert("linereg test CA", ca_key, None, ca_key, ca=True)
    files = {"ca": _write(tmp / "ca.crt", ca), "key": _write(tmp / "router.key", key)}
    files["crt"] = _write(tmp / "router.crt", _cert("localhost", key, ca.subject, ca_key, ca=False))
    (tmp / "credentials.txt").write_text("robot:robot-pw\nservice:service-pw\n")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tls/localhost:{s.getsockname()[1]}"
    conf = zenoh.Config.from_file(str(ROOT / "deploy" / "router.json5"))
    for key_path, value in {
        "listen/endpoints": [endpoint], "transport/link/tls/listen_certificate": files["crt"],
        "transport/link/tls/listen_private_key": files["key"], "transport/link/tls/root_ca_certificate": files["ca"],
        "transport/auth/usrpwd/dictionary_file": str(tmp / "credentials.txt"),
    }.items():  # fmt: skip
        conf.insert_json5(key_path, json.dumps(value))
    files["service"] = _client_config(tmp / "service.json5", "service", "service-pw", files["ca"])
    files["robot"] = _client_config(tmp / "robot.json5", "robot", "robot-pw", files["ca"])
    files["intruder"] = _client_config(tmp / "intruder.json5", "robot", "wrong-pw", files["ca"])
    config = ServiceConfig(loader="service.fake:load_fake_engine", loader_args=("", "secure"), mode="client",
                           listen=(), connect=(endpoint,), zenoh_config=files["service"], workers=1)  # fmt: skip
    with zenoh.open(conf), Service(config):
        yield endpoint, files


def _client_config(path: Path, user: str, password: str, ca: str) -> str:
    base = (ROOT / "deploy" / "robot.json5").read_text()
    conf = zenoh.Config.from_json5(base)
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(ca))
    conf.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    path.write_text(str(conf))
    return str(path)


def test_authorised_robot_gets_localize_and_info(secured):
    endpoint, files = secured
    with Client(endpoint, map_name="secure", config_file=files["robot"], wait_s=5.0) as robot:
        lines = np.array([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 9.0]])
        for _ in range(20):  # the service's queryable may take a moment to reach the router
            try:
                reg = robot.localize_segments(lines, CAMERA, timeout=1.0)
                break
            except ServiceError:
                continue
        assert reg.success
        assert robot.info()["name"] == "secure"
        assert [m for m, _ in robot.instances()] == ["secure"]


def test_denied_key_gets_nothing(secured):
    endpoint, files = secured
    with Client(endpoint, map_name="secure", config_file=files["robot"]) as robot:
        with pytest.raises(ServiceError) as e:
            robot.stats(timeout=1.0)  # operators only
        assert e.value.code == "timeout"


def test_wrong_password_cannot_connect(secured):
    endpoint, files = secured
    with pytest.raises(zenoh.ZError):
        Client(endpoint, map_name="secure", config_file=files["intruder"])


def test_plain_tcp_is_not_served(secured):
    endpoint, _ = secured
    with pytest.raises(zenoh.ZError):
        Client(endpoint.replace("tls/", "tcp/"), map_name="secure")
