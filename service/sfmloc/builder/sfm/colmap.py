"""Input 1: an existing COLMAP model and its image folder, checked against each other."""

from __future__ import annotations

from pathlib import Path

from ...errors import InputError
from ...io.colmap import Reconstruction, read_model
from .conf import SfmConf
from .inputs import check_images, list_images
from .run import CancelCheck, Progress, Reporter, quiet_colmap

_SHOW = 5


def load_colmap_input(
    model_dir: str | Path,
    image_dir: str | Path,
    conf: SfmConf | None = None,
    progress: Progress | None = None,
    should_cancel: CancelCheck | None = None,
) -> Reconstruction:
    """Read a COLMAP sparse model (text or binary) and check it against ``image_dir``.

    Raises ``ModelFormatError``/``CameraModelError`` for a bad model, ``InputError`` when the
    model's images are not all in ``image_dir`` (naming the first missing ones and how many)
    or the model has no 3D point, ``ImageDecodeError`` for an unreadable image or one whose
    size differs from its camera's.
    """
    conf = conf or SfmConf()
    rep = Reporter(progress, should_cancel)
    model_dir, image_dir = Path(model_dir), Path(image_dir)
    rep.report("input", 0.0, f"reading COLMAP model {model_dir}")
    rec = read_model(model_dir)
    if not image_dir.is_dir():
        raise InputError(f"[input] image folder {image_dir} does not exist or is not a folder")
    if not rec.images:
        raise InputError(f"[input] COLMAP model {model_dir} has no images")
    names = [im.name for im in sorted(rec.images.values(), key=lambda im: im.image_id)]
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:
        shown = ", ".join(missing[:_SHOW]) + (" ..." if len(missing) > _SHOW else "")
        if len(missing) == len(names):
            present = list_images(image_dir)[:3]
            raise InputError(
                f"[input] COLMAP model {model_dir} and image folder {image_dir} do not match: none "
                "of "
                f"the model's {len(names)} images is there (model has e.g. {shown}; folder has "
                f"{', '.join(present) if present else 'no images'})"
            )
        raise InputError(
            f"[input] {len(missing)} of the {len(names)} images of COLMAP model {model_dir} are "
            "missing "
            f"from {image_dir}: {shown}"
        )
    if not rec.points3D:
        raise InputError(f"[input] COLMAP model {model_dir} has no 3D points (points3D is empty)")
    by_name = {im.name: im for im in rec.images.values()}

    def expected(name: str) -> tuple[int, int]:
        cam = rec.cameras[by_name[name].camera_id]
        return cam.width, cam.height

    with quiet_colmap():
        check_images(image_dir, names, expected, conf, rep, what="its camera in the model")
    rep.report("input", 1.0, rec.summary())
    return rec
