"""The ``MapBuilder`` gRPC servicer (proto/sfmloc/v1/builder.proto) over a ``JobManager``.

Handlers raise; ``SyncErrorStatusInterceptor`` ends the call with the status the one table
(``sfmloc_client.errors``) gives the error: an unknown job id is NOT_FOUND
(``JobNotFoundError``), a bad request (bad name, missing folder or file) INVALID_ARGUMENT.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from sfmloc_client.cameras import camera_to_string
from sfmloc_client.pb import builder_pb2 as pb
from sfmloc_client.pb import builder_pb2_grpc as pb_grpc
from sfmloc_client.pb import common_pb2

from ..errors import InputError, JobNotFoundError
from .jobs import BuildEvent, BuildSpec, Job, JobManager, JobState

log = logging.getLogger(__name__)

_STATE = {
    JobState.QUEUED: pb.BUILD_STATE_QUEUED,
    JobState.RUNNING: pb.BUILD_STATE_RUNNING,
    JobState.SUCCEEDED: pb.BUILD_STATE_SUCCEEDED,
    JobState.FAILED: pb.BUILD_STATE_FAILED,
    JobState.CANCELLED: pb.BUILD_STATE_CANCELLED,
}


def camera_of(cam: common_pb2.Camera) -> str | None:
    """The request's camera as a camera string (None when the request has none)."""
    if not cam.model:
        return None
    return camera_to_string(cam.model, cam.width, cam.height, cam.params)


def spec_from_request(req: pb.SubmitBuildRequest, default_out: str) -> BuildSpec:
    """A ``BuildSpec`` from a request, with the paths checked now so the client hears about a
    missing folder at once rather than from a failed job."""
    kind = req.WhichOneof("input")
    if kind is None:
        raise InputError("SubmitBuild needs an input: colmap, posed_images or images_only")
    config = {}
    if req.config_json:
        try:
            config = json.loads(req.config_json)
        except json.JSONDecodeError as exc:
            raise InputError(f"config_json is not valid JSON: {exc}") from None
        if not isinstance(config, dict):
            raise InputError("config_json must be a JSON object")
    spec = BuildSpec(
        name=req.name,
        out_dir=req.out_dir or default_out,
        input_kind=kind,
        images="",
        preset=req.preset or "default",
        config=config,
        stride=max(1, req.stride),
    )
    if kind == "colmap":
        spec.colmap, spec.images = req.colmap.model_dir, req.colmap.image_dir
        _must_exist(spec.colmap, "model_dir", folder=True)
    elif kind == "posed_images":
        spec.images, spec.poses = req.posed_images.image_dir, req.posed_images.poses_file
        spec.camera = camera_of(req.posed_images.camera)
        _must_exist(spec.poses, "poses_file", folder=False)
        if spec.camera is None:
            raise InputError("posed_images needs a camera")
    else:
        spec.images = req.images_only.image_dir
        spec.camera = camera_of(req.images_only.camera)
        spec.matching = req.images_only.matching or None
        if spec.matching not in (None, "sequential", "exhaustive"):
            raise InputError(
                f"matching must be 'sequential' or 'exhaustive', got {spec.matching!r}"
            )
    _must_exist(spec.images, "image_dir", folder=True)
    if spec.camera is not None:
        from ..cameras import Camera

        Camera.parse(spec.camera)  # CameraModelError (INVALID_ARGUMENT) for a bad model
    return spec


def _must_exist(path: str, what: str, folder: bool) -> None:
    p = Path(path) if path else None
    if p is None or (folder and not p.is_dir()) or (not folder and not p.is_file()):
        kind = "folder" if folder else "file"
        raise InputError(f"{what} {path!r} is not an existing {kind} on the builder's machine")


def event_to_pb(ev: BuildEvent) -> pb.BuildEvent:
    return pb.BuildEvent(
        job_id=ev.job_id,
        state=_STATE[ev.state],
        stage=ev.stage,
        fraction=ev.fraction,
        message=ev.message,
        elapsed_s=ev.elapsed_s,
        bundle_path=ev.bundle_path,
        error=ev.error,
    )


def job_to_pb(job: Job) -> pb.BuildJob:
    return pb.BuildJob(
        job_id=job.job_id,
        name=job.spec.name,
        state=_STATE[job.state],
        stage=job.stage,
        fraction=job.fraction,
        message=job.message,
        elapsed_s=job.elapsed_s,
        bundle_path=job.bundle_path,
        error=job.error,
        input_kind=job.spec.input_kind,
        submitted_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(job.submitted)),
        ended_utc=""
        if job.ended is None
        else time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(job.ended)),
    )


class MapBuilderServicer(pb_grpc.MapBuilderServicer):
    def __init__(self, jobs: JobManager, default_out: str) -> None:
        self.jobs = jobs
        self.default_out = default_out

    def _job(self, job_id: str) -> Job:
        try:
            return self.jobs.get(job_id)
        except KeyError:
            raise JobNotFoundError(f"no build job {job_id!r}") from None

    def SubmitBuild(self, request, context):
        job = self.jobs.submit(spec_from_request(request, self.default_out))
        return pb.SubmitBuildResponse(job_id=job.job_id)

    def WatchBuild(self, request, context):
        self._job(request.job_id)
        i = 0
        while context.is_active():
            events, done = self.jobs.wait_events(request.job_id, i, timeout=1.0)
            for ev in events:
                yield event_to_pb(ev)
            i += len(events)
            if done and not events:
                return

    def ListBuilds(self, request, context):
        return pb.ListBuildsResponse(jobs=[job_to_pb(j) for j in self.jobs.list()])

    def GetBuild(self, request, context):
        return job_to_pb(self._job(request.job_id))

    def CancelBuild(self, request, context):
        self._job(request.job_id)
        return pb.CancelBuildResponse(cancelled=self.jobs.cancel(request.job_id))
