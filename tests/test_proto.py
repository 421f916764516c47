"""The committed gRPC/protobuf code matches proto/ (regenerate with `make proto`)."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO


def test_generated_code_is_up_to_date():
    r = subprocess.run(
        [sys.executable, str(REPO / "proto" / "generate.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr + r.stdout


def test_generated_modules_import_and_round_trip():
    from sfmloc_client.pb import builder_pb2, common_pb2, localization_pb2, localization_pb2_grpc

    req = localization_pb2.RelocalizeRequest(
        map="lab",
        image=common_pb2.Image(encoding=common_pb2.IMAGE_ENCODING_JPEG, data=b"\xff\xd8"),
        camera=common_pb2.Camera(
            model="PINHOLE", width=640, height=480, params=[525, 525, 320, 240]
        ),
    )
    back = localization_pb2.RelocalizeRequest.FromString(req.SerializeToString())
    assert back == req and back.camera.params[0] == 525
    assert hasattr(localization_pb2_grpc, "LocalizationStub")
    sub = builder_pb2.SubmitBuildRequest(
        name="x", colmap=builder_pb2.ColmapInput(model_dir="m", image_dir="i")
    )
    assert sub.WhichOneof("input") == "colmap"
