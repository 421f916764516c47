"""`sfmloc view`: the map served to the page (points, colours, cameras, against the bundle), the
live pose feed over real Zenoh sessions and server-sent events, and the page itself in a real
headless Chromium against a real server localizing a streamed client (the marker moves along
the synthetic ground truth; the screenshot shows the map and the marker).

The browser test needs Debian's chromium (README, Quick start: `make test-deps`); it is skipped,
with that reason, where none is installed."""

from __future__ import annotations

import hashlib
import http.client
import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from browser import Browser, find_chromium
from server_helpers import (
    camera,
    client_zenoh,
    running_server,
    server_config,
    wait_until,
    zenoh_endpoint,
)
from sfmloc.map.bundle import MapBundle
from sfmloc.viewer.http import ViewerServer
from sfmloc.viewer.live import LiveState, PoseFeed
from sfmloc_client.wire import PoseMessage, Transform, encode_pose, pose_key

VENDOR = Path(__file__).resolve().parents[1] / "service/sfmloc/viewer/static/vendor"
STATUS_RGB = {
    "TRACKING": (0x2E, 0xCC, 0x71),
    "RELOCALIZED": (0x34, 0x98, 0xDB),
    "UNVERIFIED": (0xF3, 0x9C, 0x12),
    "LOST": (0xE7, 0x4C, 0x3C),
}


def get(viewer: ViewerServer, path: str) -> tuple[int, str, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=30)
    try:
        conn.request("GET", path)
        r = conn.getresponse()
        return r.status, r.getheader("Content-Type", ""), r.read()
    finally:
        conn.close()


class Events:
    """The viewer's server-sent event stream, read on a thread."""

    def __init__(self, viewer: ViewerServer) -> None:
        self.conn = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=30)
        self.conn.request("GET", "/events")
        self.resp = self.conn.getresponse()
        assert self.resp.status == 200
        assert self.resp.getheader("Content-Type") == "text/event-stream"
        self.items: list[tuple[str, object]] = []
        self.cond = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        kind = ""
        try:
            for raw in self.resp.fp:
                line = raw.decode().rstrip("\n")
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: "):
                    with self.cond:
                        self.items.append((kind, json.loads(line[6:])))
                        self.cond.notify_all()
        except (OSError, ValueError):
            pass

    def wait(self, pred, timeout: float = 20.0) -> list:
        with self.cond:
            assert self.cond.wait_for(lambda: pred(self.items), timeout), self.items[-5:]
            return list(self.items)

    def close(self) -> None:
        self.conn.close()


def test_vendored_three_is_the_recorded_build():
    """three.min.js is the build vendor/README.md describes (tools/build_three.sh), with its
    licence beside it."""
    digest = hashlib.sha256((VENDOR / "three.min.js").read_bytes()).hexdigest()
    assert digest in (VENDOR / "README.md").read_text()
    assert "MIT License" in (VENDOR / "LICENSE-three").read_text()
    head = (VENDOR / "three.min.js").read_text()[:200]
    assert "Three.js Authors" in head and "SPDX-License-Identifier: MIT" in head


def test_map_api_serves_the_bundle(world):
    bundle = MapBundle(world.maps_dir / "room")
    with ViewerServer([world.maps_dir], LiveState(), port=0) as v:
        status, _, body = get(v, "/api/maps")
        assert status == 200 and json.loads(body) == {"maps": ["room", "room2"]}
        status, ctype, body = get(v, "/api/maps/room")
        assert status == 200 and ctype == "application/json"
        meta = json.loads(body)
        assert meta["n_points"] == meta["points_shown"] == bundle.n_points
        assert meta["build_id"] == bundle.build_id
        assert meta["scene_scale"] == pytest.approx(bundle.scene_scale, rel=1e-9)
        assert len(meta["cameras"]) == bundle.n_images
        for c, T in zip(meta["cameras"], bundle.image_cam_from_world):
            np.testing.assert_allclose(c["centre"], T.center, atol=1e-9)
            np.testing.assert_allclose(c["axes"], T.rotation, atol=1e-9)
        # "up" is opposite the mapping cameras' image-down axis: they stand upright in it.
        downs = np.array([T.rotation[1] for T in bundle.image_cam_from_world])
        assert (downs @ np.array(meta["up"]) < 0).mean() > 0.9
        status, ctype, body = get(v, "/api/maps/room/points")
        assert status == 200 and ctype == "application/octet-stream"
        n = bundle.n_points
        assert len(body) == 15 * n
        xyz = np.frombuffer(body[: 12 * n], "<f4").reshape(n, 3) + np.array(meta["origin"])
        rgb = np.frombuffer(body[12 * n :], np.uint8).reshape(n, 3)
        np.testing.assert_allclose(xyz, bundle.points_xyz, atol=1e-5)
        np.testing.assert_array_equal(rgb, bundle.array("point_rgb"))
        status, ctype, body = get(v, "/")
        assert status == 200 and ctype.startswith("text/html") and b"viewer.js" in body
        status, ctype, _ = get(v, "/static/vendor/three.min.js")
        assert status == 200 and ctype.startswith("text/javascript")


def test_large_maps_are_drawn_by_a_fixed_subset(world):
    bundle = MapBundle(world.maps_dir / "room")
    with ViewerServer([world.maps_dir], LiveState(), port=0, max_points=100) as v:
        meta = json.loads(get(v, "/api/maps/room")[2])
        assert meta["n_points"] == bundle.n_points and meta["points_shown"] == 100
        body = get(v, "/api/maps/room/points")[2]
        again = get(v, "/api/maps/room/points")[2]
    xyz = np.frombuffer(body[:1200], "<f4").reshape(100, 3) + np.array(meta["origin"])
    rgb = np.frombuffer(body[1200:], np.uint8).reshape(100, 3)
    full = bundle.points_xyz
    rows = [int(np.argmin(np.linalg.norm(full - p, axis=1))) for p in xyz]
    np.testing.assert_allclose(full[rows], xyz, atol=1e-5)  # each a map point
    np.testing.assert_array_equal(rgb, bundle.array("point_rgb")[rows])
    assert body == again


def _moved_map(world, tmp_path, scale: float, translation, name: str) -> Path:
    """The room map under a similarity (sfmloc map align's), as ``tmp_path/maps/name``."""
    from sfmloc.map.align import Sim3, write_aligned

    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    sim = Sim3(scale, rot, np.array(translation, float))
    write_aligned(MapBundle(world.maps_dir / "room"), sim, tmp_path / "maps", name)
    return tmp_path / "maps"


def test_a_map_far_from_its_origin_keeps_millimetres(world, tmp_path):
    """A map aligned to UTM-like coordinates (10^6 m away): float32 points would be 6 cm
    steps; relative to the map's origin they keep the bundle's positions."""
    maps = _moved_map(world, tmp_path, 1.0, [500_000.0, 4_000_000.0, 100.0], "far")
    bundle = MapBundle(maps / "far")
    with ViewerServer([maps], LiveState(), port=0) as v:
        meta = json.loads(get(v, "/api/maps/far")[2])
        body = get(v, "/api/maps/far/points")[2]
    n = bundle.n_points
    xyz = np.frombuffer(body[: 12 * n], "<f4").astype(np.float64).reshape(n, 3)
    err = np.abs(xyz + np.array(meta["origin"]) - bundle.points_xyz).max()
    naive = np.abs(bundle.points_xyz.astype(np.float32) - bundle.points_xyz).max()
    assert err < 1e-5 and naive > 0.01, (err, naive)


def test_bad_requests_get_clear_errors(world):
    with ViewerServer([world.maps_dir, world.spare_dir / "corrupt"], LiveState(), port=0) as v:
        status, _, body = get(v, "/api/maps/nowhere")
        assert status == 404 and "no map 'nowhere'" in json.loads(body)["error"]
        for path in ("/static/../http.py", "/static/%2e%2e/http.py", "/etc/passwd", "/api/x"):
            status, _, body = get(v, path)
            assert status == 404 and "error" in json.loads(body), path
    # The corrupt copy of "room" (flipped bytes) is found under its own root only.
    with ViewerServer([world.spare_dir / "corrupt"], LiveState(), port=0) as v:
        status, _, body = get(v, "/api/maps/room")
        assert status == 422 and "checksum mismatch" in json.loads(body)["error"]
    with pytest.raises(Exception, match="does not exist"):
        ViewerServer([world.root / "nope"], LiveState(), port=0)


def _pose(seq: int, centre, status: str = "TRACKING", client: str = "c1") -> PoseMessage:
    T = None if centre is None else Transform((0.0, 0.0, 0.0, 1.0), tuple(centre))
    inv = None if centre is None else Transform((0.0, 0.0, 0.0, 1.0), tuple(-np.array(centre)))
    return PoseMessage(
        seq=seq,
        stamp_ns=seq * 1000,
        status=status,
        cam_from_world=inv,
        world_from_cam=T,
        latency_ms=12.5,
        inliers=77,
        map="room",
        client_id=client,
        message="" if centre is not None else "too few inliers",
    )


def test_pose_stream_over_zenoh_to_server_sent_events(world):
    """Pose messages published on Zenoh reach an open page as events (position, status,
    latency), a page opening later gets each client's trajectory, and garbage on the pose key
    is counted, not fatal."""
    ep = zenoh_endpoint()
    state = LiveState()
    import zenoh

    from sfmloc_client import make_zenoh_config

    listen = make_zenoh_config("peer", listen=[ep], multicast=False)
    with (
        zenoh.open(listen) as zs,
        PoseFeed(zs, state),
        ViewerServer([world.maps_dir], state, port=0) as v,
        client_zenoh(ep) as zc,
    ):
        events = Events(v)
        events.wait(lambda items: [k for k, _ in items][:2] == ["snapshot", "summary"])
        pub = zc.declare_publisher(pose_key("room", "c1"))
        # Until the route is up, probes may be lost: publish until one arrives.
        assert wait_until(
            lambda: pub.put(encode_pose(_pose(0, [0.0, 0.0, 0.0]))) or state.poses > 0, 10, 0.05
        )
        for k in range(1, 6):
            pub.put(encode_pose(_pose(k, [0.1 * k, 0.0, 1.0])))
        pub.put(encode_pose(_pose(6, None, "LOST")))
        items = events.wait(lambda items: any(k == "pose" and d["seq"] == 6 for k, d in items))
        poses = {d["seq"]: d for k, d in items if k == "pose"}
        assert poses[5]["centre"] == pytest.approx([0.5, 0.0, 1.0])
        assert poses[5]["status"] == "TRACKING" and poses[5]["latency_ms"] == 12.5
        assert poses[5]["inliers"] == 77 and poses[5]["client"] == "c1"
        assert poses[6]["centre"] is None and poses[6]["status"] == "LOST"
        assert poses[6]["message"] == "too few inliers"
        zc.put(pose_key("room", "c2"), b"\x93not a pose")
        assert wait_until(lambda: state.summary()["bad_messages"] == 1, 10)
        late = Events(v)
        snap = late.wait(lambda items: bool(items))[0]
        assert snap[0] == "snapshot"
        (c1,) = snap[1]
        trail = np.array(c1["trail"])
        assert c1["client"] == "c1" and c1["status"] == "LOST" and len(trail) >= 6
        np.testing.assert_allclose(trail[-5:, 0], [0.1, 0.2, 0.3, 0.4, 0.5])
        status = json.loads(get(v, "/api/status")[2])
        assert status["bad_messages"] == 1 and "c2" in status["last_bad"]
        events.close()
        late.close()


def test_live_state_rates_ages_and_forgets():
    state = LiveState(trail=3, forget_after_s=10.0)
    for k in range(5):
        state.update(_pose(k, [float(k), 0.0, 0.0]), now=100.0 + 0.5 * k)
    state.update(_pose(0, [9.0, 9.0, 9.0], client="other"), now=101.0)
    (c1,) = [c for c in state.snapshot(now=102.5) if c["client"] == "c1"]
    assert [p[0] for p in c1["trail"]] == [2.0, 3.0, 4.0]  # the last --trail positions
    assert c1["age_s"] == pytest.approx(0.5)
    s = {c["client"]: c for c in state.summary(now=102.5)["clients"]}
    assert s["c1"]["rate_hz"] == pytest.approx(4 / 2.0)  # poses in the last 2 s
    assert s["c1"]["n_poses"] == 5 and s["other"]["age_s"] == pytest.approx(1.5)
    s = state.summary(now=111.5)["clients"]  # "other" silent 10.5 s, c1 9.5 s
    assert [c["client"] for c in s] == ["c1"] and s[0]["rate_hz"] == 0


def _status_pixels(png: bytes, status: str) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    near = np.abs(img.astype(int) - np.array(STATUS_RGB[status])).max(axis=2) < 30
    return np.argwhere(near)  # (row, col)


@pytest.mark.skipif(
    find_chromium() is None,
    reason="no chromium on PATH: the viewer's browser test needs Debian's chromium "
    "(make test-deps, or apt-get install -y chromium)",
)
def test_page_shows_the_map_and_a_streamed_client_moving(world, tmp_path):
    """The real thing: a server localizes a client streaming the synthetic video over Zenoh;
    the viewer listens; Chromium loads the page, which draws the map and moves the client's
    marker along the exact ground truth."""
    ep = zenoh_endpoint()
    state = LiveState()
    stop = threading.Event()
    bundle = MapBundle(world.maps_dir / "room")

    def stream(z) -> None:
        from sfmloc_client import FrameStreamer

        with FrameStreamer(z, "room", "walker", camera(world), encoding="png") as fs:
            fs.wait_for_server(20)
            for k, data in enumerate(world.png):
                if stop.is_set():
                    return
                fs.publish(data=data, encoding="png", stamp_ns=int(k * 1e9 / 30), seq=k)
                time.sleep(0.15)  # slow enough to be seen mid-way

    def shot_and_state(b: Browser) -> tuple[bytes, dict, list[float]]:
        # The screenshot shows the pose read before and after it only when no pose came in
        # between (one comes every 0.15 s): a dot drawn for the next pose sat a few pixels off
        # the position read after the shot (a clean clone read 12 status pixels near it, not 20).
        expr = "[window.sfmlocView.clients.walker, window.sfmlocView.screen('walker')]"
        for _ in range(50):
            before, _xy = b.evaluate(expr)
            png = b.screenshot()
            c, xy = b.evaluate(expr)
            if c["seq"] == before["seq"]:
                return png, c, xy
        raise AssertionError("a new pose arrived during each of 50 screenshots")

    with (
        running_server(server_config(world, ep)),
        client_zenoh(ep) as zv,
        PoseFeed(zv, state),
        ViewerServer([world.maps_dir], state, port=0) as v,
        Browser() as b,
    ):
        b.open(v.url + "?map=room", width=1000, height=700)
        view = b.wait_for("window.sfmlocView && window.sfmlocView.ready && window.sfmlocView")
        assert view["error"] is None, (view, b.console)
        assert view["map"] == "room" and view["points"] == bundle.n_points
        assert view["cameras"] == bundle.n_images
        blank = b.screenshot()
        with client_zenoh(ep) as zc:
            t = threading.Thread(target=stream, args=(zc,), daemon=True)
            t.start()
            try:
                b.wait_for(
                    "(c => c && c.centre && c.status !== 'LOST')(window.sfmlocView.clients.walker)",
                    60,
                )
                shot1, first, screen1 = shot_and_state(b)
                b.wait_for(
                    f"(c => c.status !== 'LOST' && c.seq >= {first['seq'] + 8})"
                    "(window.sfmlocView.clients.walker)",
                    60,
                )
                shot2, later, screen2 = shot_and_state(b)
            finally:
                stop.set()
                t.join(30)
    (tmp_path / "viewer.png").write_bytes(shot2)
    # The marker is where the server says, and that is the ground truth of that frame.
    for c in (first, later):
        gt = world.gt_cam_from_world[c["seq"]].center
        assert np.linalg.norm(np.array(c["centre"]) - gt) < 0.05, (c, gt)
    assert np.linalg.norm(np.array(later["centre"]) - np.array(first["centre"])) > 0.05
    assert later["trail"] > first["trail"] and later["latency_ms"] > 0
    moved_px = np.hypot(screen2[0] - screen1[0], screen2[1] - screen1[1])
    assert moved_px > 2, moved_px  # it moved on screen
    # Not blank: the map's points and cameras are drawn (many grey levels: texture colours,
    # frusta), and the client's status dot is where the page projects its centre.
    import cv2

    img = cv2.imdecode(np.frombuffer(blank, np.uint8), cv2.IMREAD_GRAYSCALE)
    scene = img[150:650, 50:950]  # below the panel, above the legend
    assert scene.std() > 8 and len(np.unique(scene)) > 40
    for shot, (x, y) in ((shot1, screen1), (shot2, screen2)):
        # any status but LOST: the dot is drawn in the status of the newest pose
        near = sum(
            int((np.hypot(d[:, 1] - x, d[:, 0] - y) < 12).sum())
            for d in (_status_pixels(shot, s) for s in ("TRACKING", "RELOCALIZED", "UNVERIFIED"))
        )
        assert near >= 20, (x, y, near)


def test_view_command_serves_until_interrupted(world):
    """SIGINT stops it (exit 130), also when it was started with SIGINT ignored, as a shell
    starts a background command (`make test &`): it failed in every such full-suite run."""
    import signal
    import subprocess
    import sys

    ignoring = ["sh", "-c", "trap '' INT; exec \"$@\"", "sh"]  # what a background job gets
    probe = [sys.executable, "-c", "import signal as s; print(s.getsignal(s.SIGINT) == s.SIG_IGN)"]
    assert subprocess.run(ignoring + probe, capture_output=True, text=True).stdout.strip() == (
        "True"
    )
    view = [sys.executable, "-m", "sfmloc", "view", "--maps", str(world.maps_dir), "--port", "0"]
    proc = subprocess.Popen(
        ignoring + view + ["--zenoh-listen", zenoh_endpoint(), "--no-multicast"],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        url = None
        for line in proc.stderr:  # type: ignore[union-attr]
            m = re.search(r"sfmloc view on (http://\S+/) \(maps: room, room2\)", line)
            if m:
                url = m.group(1)
                break
        assert url, "no address printed"
        port = int(url.rsplit(":", 1)[1].rstrip("/"))
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/api/maps")
        assert json.loads(conn.getresponse().read()) == {"maps": ["room", "room2"]}
        conn.close()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
        assert proc.returncode == 130, err[-2000:]
        assert "stopped (SIGINT)" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    r = subprocess.run(
        [sys.executable, "-m", "sfmloc", "view", "--maps", str(world.root / "nope")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "maps folder" in r.stderr and "does not exist" in r.stderr


@pytest.mark.skipif(
    find_chromium() is None,
    reason="no chromium on PATH: the viewer's browser test needs Debian's chromium "
    "(make test-deps, or apt-get install -y chromium)",
)
@pytest.mark.parametrize(
    "scale, translation",
    [(0.001, [0.0, 0.0, 0.0]), (1000.0, [0.0, 0.0, 0.0]), (1.0, [500_000.0, 4e6, 100.0])],
    ids=["millimetre-room", "kilometre-room", "utm"],
)
def test_page_draws_maps_of_any_scale_and_place(world, tmp_path, scale, translation):
    """The same room at 1/1000 and 1000x its size, and 10^6 m from the origin: the page frames
    the map (not blank) and draws a client where its pose says, inside the view."""
    from sfmloc.map.align import Sim3

    maps = _moved_map(world, tmp_path, scale, translation, "moved")
    bundle = MapBundle(maps / "moved")
    c, s = np.cos(0.7), np.sin(0.7)
    sim = Sim3(scale, np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), np.array(translation))
    state = LiveState()
    with ViewerServer([maps], state, port=0) as v, Browser() as b:
        b.open(v.url, width=900, height=650)
        view = b.wait_for("window.sfmlocView && window.sfmlocView.ready && window.sfmlocView")
        assert view["error"] is None and view["points"] == bundle.n_points, (view, b.console)
        b.wait_for("window.sfmlocView.connected")
        for k in range(0, 30, 3):
            T = sim.transform_cam_from_world(world.gt_cam_from_world[k]).inverse()
            pose = _pose(k, T.translation, client="probe")
            pose.map = "moved"
            state.update(pose)
        got = b.wait_for("(c => c && c.seq === 27 && c)(window.sfmlocView.clients.probe)")
        x, y = b.evaluate("window.sfmlocView.screen('probe')")
        png = b.screenshot()
    expect = sim.transform_cam_from_world(world.gt_cam_from_world[27]).inverse().translation
    np.testing.assert_allclose(got["centre"], expect, rtol=1e-12)
    assert got["trail"] == 10
    assert 0 < x < 900 and 0 < y < 650, (x, y)
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    scene = img[150:600, 50:850]
    assert scene.std() > 8 and len(np.unique(scene)) > 40
    dots = _status_pixels(png, "TRACKING")
    assert (np.hypot(dots[:, 1] - x, dots[:, 0] - y) < 12).sum() >= 20


@pytest.mark.skipif(
    find_chromium() is None,
    reason="no chromium on PATH: the viewer's browser test needs Debian's chromium "
    "(make test-deps, or apt-get install -y chromium)",
)
def test_page_shows_lost_then_drops_a_silent_client(world):
    state = LiveState(forget_after_s=2.0)
    with ViewerServer([world.maps_dir], state, port=0) as v, Browser() as b:
        b.open(v.url + "?map=room", width=800, height=600)
        b.wait_for("window.sfmlocView && window.sfmlocView.ready && window.sfmlocView.connected")
        centre = world.gt_cam_from_world[0].center
        state.update(_pose(0, centre, client="gone"))
        state.update(_pose(1, None, "LOST", client="gone"))
        lost = b.wait_for("(c => c && c.seq === 1 && c)(window.sfmlocView.clients.gone)")
        assert lost["status"] == "LOST"
        np.testing.assert_allclose(lost["centre"], centre)  # drawn at its last pose
        x, y = b.evaluate("window.sfmlocView.screen('gone')")
        dots = _status_pixels(b.screenshot(), "LOST")
        assert (np.hypot(dots[:, 1] - x, dots[:, 0] - y) < 12).sum() >= 20
        assert "too few inliers" in b.evaluate("document.querySelector('#clients').innerText")
        b.wait_for("!window.sfmlocView.clients.gone", 15)  # forgotten after 2 s of silence
        # The table is redrawn on the page's next update, a moment after the state forgets it.
        b.wait_for("document.querySelector('#clients tbody').children.length === 0", 5)
