"""Zenoh access control per client id (issue 12), with real Zenoh sessions over mutual TLS
against a real server running the committed ``docker/zenoh-server-acl.json5``: a device
streams and reads poses under its own id; another device's frames under that id and its
subscription to that id's poses are refused by the server's Zenoh runtime; a device without a
certificate cannot connect."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from server_helpers import (
    camera,
    running_server,
    server_config,
    stream_lockstep,
)
from sfmloc.testing import free_port
from sfmloc_client import FrameStreamer
from sfmloc_client.discovery import list_server_ids, query_servers

REPO = Path(__file__).resolve().parents[1]
SERVER_FILE = REPO / "docker" / "zenoh-server-acl.json5"
DEVICE_FILE = REPO / "docker" / "zenoh-device.json5"


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """A CA; the server's certificate (localhost); drone-1 and drone-2 (their common names)."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: TLS certificates cannot be made for the test")
    d = tmp_path_factory.mktemp("zenoh-pki")
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    _openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
             "-subj", "/CN=sfmloc-test-ca", cwd=d)  # fmt: skip
    (d / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name in ("server", "drone-1", "drone-2"):
        _openssl("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr",
                 "-subj", f"/CN={name}", cwd=d)  # fmt: skip
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                 "-CAcreateserial", "-out", f"{name}.pem", "-days", "2",
                 "-extfile", "san.ext", cwd=d)  # fmt: skip
    return d


def _device(pki: Path, tmp: Path, name: str | None, endpoint: str) -> zenoh.Session:
    """A device session from the committed device file, with this test's certificates."""
    text = DEVICE_FILE.read_text().replace("tls/sfmloc-server:7447", endpoint)
    text = text.replace("/certs/", f"{pki}/").replace("drone-1", name or "none")
    path = tmp / f"device-{name}.json5"
    path.write_text(text)
    conf = zenoh.Config.from_file(str(path))
    if name is None:  # no client certificate at all
        conf.insert_json5("transport/link/tls/connect_certificate", "null")
        conf.insert_json5("transport/link/tls/connect_private_key", "null")
    return zenoh.open(conf)


def test_committed_config_is_the_generators_output():
    from sfmloc.server.zenoh_acl import render, server_config

    conf = server_config(["drone-1", "drone-2"], ["builder"])
    assert SERVER_FILE.read_text() == render(
        conf, "sfmloc server Zenoh configuration (sfmloc auth zenoh-acl)"
    )
    zenoh.Config.from_file(str(SERVER_FILE))  # zenoh accepts it (schema of the installed one)
    zenoh.Config.from_file(str(DEVICE_FILE))


def test_the_readme_command_writes_the_committed_config(tmp_path):
    """README's `sfmloc auth zenoh-acl --device drone-1 --device drone-2 --admin builder
    --tls-ca /certs/ca.pem ... --out FILE` (the command path, not only its functions) writes
    docker/zenoh-server-acl.json5, as README says."""
    out = tmp_path / "zenoh-server.json5"
    certs = ["--tls-ca", "/certs/ca.pem", "--tls-cert", "/certs/server.pem"]
    r = subprocess.run(
        [sys.executable, "-m", "sfmloc", "auth", "zenoh-acl", "--device", "drone-1"]
        + ["--device", "drone-2", "--admin", "builder", *certs]
        + ["--tls-key", "/certs/server.key", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert out.read_text() == SERVER_FILE.read_text()


def test_acl_refuses_bad_lists():
    from sfmloc.errors import SfmlocError
    from sfmloc.server.zenoh_acl import acl_section

    for devices, admins in (([], []), (["a", "a"], []), (["a/b"], []), (["*"], [])):
        with pytest.raises(SfmlocError):
            acl_section(devices, admins)


def test_each_device_streams_and_reads_poses_only_under_its_own_id(world, pki, tmp_path):
    endpoint = f"tls/localhost:{free_port()}"
    conf_file = tmp_path / "server.json5"
    conf_file.write_text(SERVER_FILE.read_text().replace("/certs/", f"{pki}/"))
    conf = server_config(world, endpoint, zenoh={"config_file": str(conf_file)})
    with running_server(conf) as srv:
        assert srv.server is not None
        loc = srv.server.facade
        with (
            _device(pki, tmp_path, "drone-1", endpoint) as z1,
            _device(pki, tmp_path, "drone-2", endpoint) as z2,
        ):
            spied: list = []  # drone-2 listening on drone-1's poses (and error replies)
            with z2.declare_subscriber("sfmloc/room/drone-1/pose", spied.append):
                # drone-2 publishes valid frames under drone-1's id, then its own: its own frames
                # are answered, so the forged ones (sent before on the same link) reached the
                # server's Zenoh runtime and were dropped there (no session, no error reply).
                with FrameStreamer(z2, "room", "drone-1", camera(world), encoding="png") as fs:
                    for png in world.png[:3]:
                        fs.publish(data=png, encoding="png")
                own2 = stream_lockstep(z2, "room", "drone-2", world, n=2)
                assert [p.seq for p in own2] == [0, 1]
                assert not any(s.client_id == "drone-1" for s in loc.list_sessions())

                # The same forgery addressed to the server's own frame key: dropped too.
                sid = srv.server.server_id
                with FrameStreamer(
                    z2, "room", "drone-1", camera(world), encoding="png", server=sid
                ) as fs:
                    fs.publish(data=world.png[0], encoding="png")
                own2 = stream_lockstep(z2, "room", "drone-2", world, n=1, server=sid)
                assert [p.seq for p in own2] == [0]
                assert not any(s.client_id == "drone-1" for s in loc.list_sessions())

                # drone-1 streams as itself: every frame answered, localized (the last two
                # addressed to the server).
                own1 = stream_lockstep(z1, "room", "drone-1", world, n=3)
                own1 += stream_lockstep(z1, "room", "drone-1", world, n=2, server=sid)
                assert [p.seq for p in own1] == [0, 1, 2, 0, 1]
                assert sum(p.localized for p in own1) >= 4
                # drone-2's subscription to drone-1's poses got none of them (a last round trip
                # of drone-2's own orders it after every pose drone-1 got).
                stream_lockstep(z2, "room", "drone-2", world, n=1)
                assert spied == []
            sessions = {s.client_id: s for s in loc.list_sessions()}
            assert sessions["drone-1"].frames == 5 and sessions["drone-2"].frames == 4
            # Discovery stays open to devices: the server's token and its info queryable.
            assert list_server_ids(z1, 5.0) == [srv.server.server_id]
            assert [i.server_id for i in query_servers(z1, 5.0)] == [srv.server.server_id]

        # Without a client certificate the TLS handshake fails: no session at all.
        with pytest.raises(Exception, match="(?i)unable to connect"):
            _device(pki, tmp_path, None, endpoint)


def test_devices_identified_by_zenoh_user_name(world, pki, tmp_path):
    """--identify user: TLS without client certificates; Zenoh user names and passwords
    (transport/auth/usrpwd) name the devices."""
    from sfmloc.server.zenoh_acl import render
    from sfmloc.server.zenoh_acl import server_config as acl_server_config

    users = tmp_path / "users.txt"
    users.write_text("drone-1:pw-one\ndrone-2:pw-two\n")
    conf_file = tmp_path / "server-users.json5"
    conf_file.write_text(
        render(
            acl_server_config(
                ["drone-1", "drone-2"],
                identify="user",
                tls_ca=str(pki / "ca.pem"),
                tls_cert=str(pki / "server.pem"),
                tls_key=str(pki / "server.key"),
                users_file=str(users),
            )
        )
    )
    endpoint = f"tls/localhost:{free_port()}"

    def device(user: str, password: str) -> zenoh.Session:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("connect/endpoints", f'["{endpoint}"]')
        c.insert_json5("transport/link/tls/root_ca_certificate", f'"{pki / "ca.pem"}"')
        c.insert_json5("transport/auth/usrpwd/user", f'"{user}"')
        c.insert_json5("transport/auth/usrpwd/password", f'"{password}"')
        return zenoh.open(c)

    conf = server_config(world, endpoint, zenoh={"config_file": str(conf_file)})
    with running_server(conf) as srv:
        assert srv.server is not None
        with device("drone-1", "pw-one") as z1, device("drone-2", "pw-two") as z2:
            with FrameStreamer(z2, "room", "drone-1", camera(world), encoding="png") as fs:
                fs.publish(data=world.png[0], encoding="png")  # forged: dropped
            assert [p.seq for p in stream_lockstep(z2, "room", "drone-2", world, n=1)] == [0]
            assert not any(s.client_id == "drone-1" for s in srv.server.facade.list_sessions())
            own = stream_lockstep(z1, "room", "drone-1", world, n=2)
            assert [p.seq for p in own] == [0, 1]
        with pytest.raises(Exception, match="(?i)unable to connect"):
            device("drone-1", "wrong-password")
