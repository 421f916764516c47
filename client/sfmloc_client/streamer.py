"""Publishing frames: ``FrameStreamer`` sends one client's frames to
``sfmloc/<map>/<client>/frame``.

Two pacing modes in ``run()``: at a fixed rate (``fps``; the server drops stale frames when
it cannot keep up, latest-frame-only), or in lockstep (``lockstep=True``: the next frame goes
out once the previous one's pose is back, i.e. as fast as the server answers).
"""

from __future__ import annotations

import collections
import itertools
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .images import encode_image
from .keys import check_name
from .placement import Placement
from .sources import SourceFrame, array_frames, open_source
from .subscriber import PoseSubscriber
from .wire import CameraSpec, Frame, PoseMessage, Transform, encode_frame, frame_key

log = logging.getLogger(__name__)


# Frames in a row without an answer that make an outage (the server stopped, the network
# dropped): reported, while the stream goes on and resumes when answers come back.
OUTAGE_FRAMES = 5


def unanswered(last_sent_seq: int, poses: PoseSubscriber | None) -> int:
    """Frames sent after the newest one the server answered (an outage when it grows)."""
    return 0 if poses is None else max(0, last_sent_seq - max(poses.max_seq, -1))


SEND_MS_KEEP = 1000


@dataclass
class StreamStats:
    sent: int = 0
    last_seq: int = -1
    started: float = 0.0
    ended: float = 0.0
    # Client-side encode + publish time (ms) of the last SEND_MS_KEEP frames: a stream lives for
    # hours (a list of every frame grew ~3 MB an hour at 30 Hz).
    send_ms: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=SEND_MS_KEEP)
    )
    # With ``poses``: the most frames ever sent after the newest answered one, and how many
    # times that reached ``OUTAGE_FRAMES`` (each outage counted once, however long).
    max_unanswered: int = 0
    outages: int = 0
    undelivered: int = 0  # frames sent while no server subscribed (lost; see FrameStreamer)

    @property
    def duration_s(self) -> float:
        return max(1e-9, self.ended - self.started)

    @property
    def rate_hz(self) -> float:
        return self.sent / self.duration_s


class FrameStreamer:
    """Frames of one camera, published with Zenoh.

    ``encoding`` is how numpy images are sent (``jpeg`` by default: ~15x smaller than raw at
    640x480; ``gray8`` avoids encode/decode costs on loopback). Frames go out with express
    delivery and congestion control BLOCK by default: a frame is fragmented into many batches,
    and with DROP Zenoh discards whole frames whenever its queue is momentarily busy (on
    loopback, two threads bursting 100 frames of 500 kB each lost 3 of 200; two streaming
    clients sharing a session lost a first frame). Staleness is handled by
    the server, which keeps only the newest frame per client; ``congestion="drop"`` suits a
    sender that must never wait (the frame is then lost instead).
    """

    def __init__(
        self,
        session: Any,
        map_name: str,
        client_id: str,
        camera: CameraSpec | str,
        *,
        encoding: str = "jpeg",
        jpeg_quality: int = 90,
        congestion: str = "block",
        server: str | None = None,
        placement_policy: str = "rendezvous",
    ) -> None:
        """``server``: None sends frames to every server hosting the map (one server: the
        usual case); a server id names the one that answers; ``"auto"`` picks one of the ready
        servers hosting the map (``placement.py``) and moves to another when it disappears."""
        import zenoh

        if congestion not in ("drop", "block"):
            raise ValueError(f"congestion must be 'drop' or 'block', got {congestion!r}")

        self.key = frame_key(map_name, client_id)
        self.placement: Placement | None = None
        self._target = ""
        self._next_pick = 0.0
        if server == "auto":
            self.placement = Placement(session, map_name, client_id, placement_policy)
        elif server:
            self._target = check_name(server, "server id")
        self.map_name, self.client_id = map_name, client_id
        # A camera.json path or "MODEL w h params..." as well as a CameraSpec.
        self.camera = camera if isinstance(camera, CameraSpec) else CameraSpec.parse(camera)
        self.encoding = encoding
        self.jpeg_quality = jpeg_quality
        self.next_seq = 0
        self.last_put_time = 0.0
        # Frames published while no server subscribed to our key: Zenoh drops them without a
        # word (a client that starts before its server, or during a server restart), so they
        # are counted here and logged (the first, then every 100th).
        self.undelivered = 0
        # The server binds our session to this id: another device under our client id is refused.
        self.source = str(session.zid())
        self._session = session
        self._publisher_options = {
            "priority": zenoh.Priority.DATA_HIGH,
            "congestion_control": zenoh.CongestionControl.DROP
            if congestion == "drop"
            else zenoh.CongestionControl.BLOCK,
            "express": True,
        }
        # id(publisher) -> (its matching status as Zenoh last reported it, the listener)
        self._reported: dict[int, tuple[list[bool], Any]] = {}
        self._pub = self._declare(self.key)
        self._addressed: dict[str, Any] = {}  # server id -> publisher on its frame key
        # (cam_from_world, server id, time.monotonic()) of the last localized pose (note_pose)
        self._last_pose: tuple[Transform, str, float] | None = None
        self.handover_max_age_s = 5.0
        # How long a new addressed publisher waits for its match status (see _publisher).
        self.match_wait_s = 1.0

    def _declare(self, key: str) -> Any:
        import zenoh

        pub = self._session.declare_publisher(key, **self._publisher_options)
        # Zenoh reports each change of the publisher's matching status: ``publish`` reads the
        # last report instead of asking Zenoh for every frame (``matching_status`` cost ~75 us
        # of CPU per frame in a streaming client, 0.6 us in a hot loop: issue 10, the client's
        # CPU per frame). The callback only stores a bool, so it runs on Zenoh's own thread
        # (``indirect=False``: no Python thread per publisher for it).
        reported = [False]

        def on_status(status: Any) -> None:
            reported[0] = bool(getattr(status, "matching", status))

        listener = pub.declare_matching_listener(zenoh.handlers.Callback(on_status, indirect=False))
        self._reported[id(pub)] = (reported, listener)
        return pub

    def _undeclare(self, pub: Any) -> None:
        reported = self._reported.pop(id(pub), None)
        for obj in (reported[1] if reported else None, pub):
            try:
                if obj is not None:
                    obj.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closed already
                pass

    @staticmethod
    def _matched(pub: Any) -> bool:
        status = pub.matching_status  # a MatchingStatus (the stubs say bool)
        return bool(getattr(status, "matching", status))

    def _delivers(self, pub: Any) -> bool:
        """Whether a server subscribes to ``pub``'s key: matching as Zenoh last reported it,
        else (no report of a match yet: a new publisher, or no server) Zenoh asked now, so a
        frame is counted undelivered exactly as when Zenoh was asked for every frame."""
        reported = self._reported.get(id(pub))
        return (reported is not None and reported[0][0]) or self._matched(pub)

    def server_present(self) -> bool:
        """Whether a subscriber (a server) matches this client's frame key right now."""
        return self._matched(self._pub)

    def wait_for_server(self, timeout: float = 5.0) -> bool:
        """Wait until a server subscribes to our frames (frames sent before would be lost)."""
        deadline = time.monotonic() + timeout
        while not self.server_present():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def publish(
        self,
        image: np.ndarray | None = None,
        *,
        data: bytes | None = None,
        encoding: str | None = None,
        seq: int | None = None,
        stamp_ns: int | None = None,
        prior: Transform | None = None,
    ) -> int:
        """Send one frame (a numpy image, or already-encoded ``data`` in ``encoding``); returns
        its ``seq`` (consecutive from 0 unless given). ``prior``: an outside estimate of its
        ``cam_from_world`` (wire.Frame's ``prior``, e.g. from GPS/IMU); without one, a frame
        to a server that has not localized this client yet carries the last pose another
        server gave (``note_pose``): after a failover the new server searches around it."""
        if data is None:
            if image is None:
                raise ValueError("publish() needs an image or data")
            encoding = self.encoding
            data = encode_image(image, encoding, self.jpeg_quality)
        elif encoding is None:
            raise ValueError("publish(data=...) needs its encoding")
        seq = self.next_seq if seq is None else int(seq)
        self.next_seq = seq + 1
        stamp_ns = time.time_ns() if stamp_ns is None else int(stamp_ns)
        target = self.target()
        if prior is None:
            prior = self._handover_prior(target)
        payload = encode_frame(
            Frame(seq, stamp_ns, self.camera, encoding, data, self.source, target, prior)
        )
        pub = self._publisher(target)
        # When the frame went out (perf_counter): a large frame reaches the server before
        # put() returns, so latency is measured from here, not from after publish().
        if not self._delivers(pub):
            self.undelivered += 1
            if self.undelivered % 100 == 1:
                log.warning(
                    "frame %d not delivered: no server subscribes to %s (%d so far)",
                    seq,
                    pub.key_expr,  # the addressed key when frames name a server
                    self.undelivered,
                )
        self.last_put_time = time.perf_counter()
        pub.put(payload)
        return seq

    def note_pose(self, pose: PoseMessage | None) -> None:
        """Remember the last localized pose and the server that gave it (``run()`` does this
        with its ``poses``; a caller of ``publish()`` passes what its PoseSubscriber gets):
        the handover prior after a move to another server."""
        if pose is not None and pose.localized and pose.cam_from_world is not None:
            self._last_pose = (pose.cam_from_world, pose.server_id, time.monotonic())

    def _handover_prior(self, target: str) -> Transform | None:
        """The last pose, for a frame to a server other than the one that gave it, while it
        is at most ``handover_max_age_s`` old (then the new server's own poses take over)."""
        last = self._last_pose
        if last is None or not target or last[1] == target:
            return None
        pose, _, t = last
        return pose if time.monotonic() - t <= self.handover_max_age_s else None

    def _publisher(self, target: str) -> Any:
        """The publisher of frames for ``target`` (a server id: its own key, which no other
        server receives; "": the map's key, every server hosting it)."""
        if not target:
            return self._pub
        pub = self._addressed.get(target)
        if pub is None:
            if len(self._addressed) >= 16:  # servers come and go over weeks: keep a few
                self._undeclare(self._addressed.pop(next(iter(self._addressed))))
            pub = self._declare(frame_key(self.map_name, self.client_id, target))
            self._addressed[target] = pub
            # A new publisher's match status is not known at once: through a router it is
            # False until the router answers (~ms), while the router already forwards what is
            # put. Wait for it (a bounded while: a frame to a server that really is gone is
            # then counted undelivered, as it should be) so the count only holds lost frames.
            deadline = time.monotonic() + self.match_wait_s
            while not self._matched(pub) and time.monotonic() < deadline:
                time.sleep(0.002)
        return pub

    @property
    def server(self) -> str:
        """The server this client's frames go to now ("": every server hosting the map)."""
        return (self.placement.owner or "") if self.placement is not None else self._target

    def target(self) -> str:
        """The server id the next frame names: with ``server="auto"``, picked on the first frame
        and picked again when the owner's liveliness token is gone (a server query of up to
        1 s, at most every 0.5 s while no server hosts the map; frames meanwhile name none)."""
        p = self.placement
        if p is None:
            return self._target
        if p.owner is not None and not p.owner_lost:
            return p.owner
        now = time.monotonic()
        if now >= self._next_pick:
            before = p.owner
            chosen = p.repick() if before is not None else p.pick()
            self._next_pick = now + 0.5
            if chosen != before:
                log.info("frames for %s now go to server %s", self.map_name, chosen or "(none)")
        return p.owner or ""

    def run(
        self,
        source: Any,
        *,
        fps: float | None = None,
        lockstep: bool = False,
        poses: PoseSubscriber | None = None,
        pose_timeout: float = 2.0,
        max_frames: int | None = None,
        on_sent: Callable[[int, SourceFrame, float], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        wait_server: float = 5.0,
    ) -> StreamStats:
        """Stream ``source`` (anything ``open_source`` takes, or an iterable of ``SourceFrame``).

        ``fps``: send at this rate (None: as fast as possible, or in lockstep); ``lockstep``:
        wait for each frame's pose (needs ``poses``; a pose that does not come within
        ``pose_timeout`` is given up on). Stamps are the send time unless the source has its own.
        ``on_sent(seq, frame, t_put)`` is called after each frame, ``t_put`` being the
        ``time.perf_counter()`` at which it went out (for latency measurements).
        ``wait_server``: seconds to wait for a server before the first frame (a frame published
        before any server subscribes is lost); frames sent without one are counted in
        ``stats.undelivered``.
        """
        if lockstep and poses is None:
            raise ValueError("lockstep streaming needs a PoseSubscriber (poses=...)")
        frames = self._frames(source)
        if wait_server > 0 and not self.wait_for_server(wait_server):
            log.warning("no server subscribes to %s after %.1f s: streaming anyway", self.key,
                        wait_server)  # fmt: skip
        undelivered0 = self.undelivered
        stats = StreamStats(started=time.monotonic())
        period = 1.0 / fps if fps else 0.0
        t_next = time.monotonic()
        in_outage = False
        for k, fr in enumerate(frames):
            if (max_frames is not None and k >= max_frames) or (should_stop and should_stop()):
                break
            if period:
                delay = t_next - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                t_next = max(t_next + period, time.monotonic() - period)  # no burst after a stall
            t0 = time.perf_counter()
            if poses is not None:
                self.note_pose(poses.last)
            if fr.data is not None:
                seq = self.publish(
                    data=fr.data, encoding=fr.encoding, stamp_ns=fr.stamp_ns, prior=fr.prior
                )
            else:
                seq = self.publish(fr.image, stamp_ns=fr.stamp_ns, prior=fr.prior)
            stats.send_ms.append((time.perf_counter() - t0) * 1e3)
            stats.sent += 1
            stats.last_seq = seq
            gap = unanswered(seq - 1, poses)  # the frame just sent cannot be answered yet
            stats.max_unanswered = max(stats.max_unanswered, gap)
            if gap >= OUTAGE_FRAMES and not in_outage:
                stats.outages += 1
                log.warning("no answer for %d frames (since frame %d)", gap, seq - gap)
            in_outage = gap >= OUTAGE_FRAMES
            if on_sent is not None:
                on_sent(seq, fr, self.last_put_time)
            if lockstep:
                assert poses is not None
                if not poses.wait_for(seq, pose_timeout):
                    log.warning("no pose for frame %d within %.1f s", seq, pose_timeout)
        stats.ended = time.monotonic()
        stats.undelivered = self.undelivered - undelivered0
        return stats

    def _frames(self, source: Any) -> Iterator[SourceFrame]:
        passthrough = self.encoding if self.encoding in ("jpeg", "png") else None
        if isinstance(source, (str, Path, int, np.ndarray)):
            return open_source(source, passthrough=passthrough)
        it = iter(source)
        first = next(it, None)
        if first is None:
            return iter(())
        rest = itertools.chain([first], it)
        return rest if isinstance(first, SourceFrame) else array_frames(rest)

    def close(self) -> None:
        if self.placement is not None:
            self.placement.close()
        for pub in (self._pub, *self._addressed.values()):
            self._undeclare(pub)
        self._addressed.clear()

    def __enter__(self) -> FrameStreamer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
