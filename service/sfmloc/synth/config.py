"""Configuration of the synthetic scene generator (hloc style: defaults + named presets).

``SynthConf()`` holds the defaults; ``confs`` maps a preset name to a dict of changes that
``sfmloc.config.merge_presets`` merges over them; command-line flags override both.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ..config import StrictModel, merge_presets

TrajectoryKind = Literal["walk", "flight", "orbit"]
TRAJECTORY_KINDS: tuple[str, ...] = ("walk", "flight", "orbit")
SCENES: tuple[str, ...] = ("room",)


class SceneConf(StrictModel):
    """Geometry and texture of the ``room`` scene (metres)."""

    name: Literal["room"] = "room"
    # Room extent along world x, y, z (z up, floor at z = 0, one corner at the origin).
    size: tuple[float, float, float] = (8.0, 5.0, 3.0)
    # Number of furniture boxes, the table counting as one (it is a slab on four legs).
    n_boxes: int = Field(7, ge=0, le=8)
    # Nominal texel edge (m): 4 mm keeps a wall sharp down to ~1.7 m at f = 525.
    texel_size: float = Field(0.004, ge=0.001, le=0.05)
    # Gray levels of per-texel grain (paper/plaster) so nothing is one flat colour.
    grain: float = Field(2.0, ge=0.0, le=20.0)
    # Every wall gets the same texture (in a square room the four walls are then identical):
    # an ambiguous scene, to test that repeated structure never yields a confident wrong pose.
    repeat_walls: bool = False


class RenderConf(StrictModel):
    # Standard deviation of the per-pixel, per-channel Gaussian noise, gray levels (0 = none).
    noise_sigma: float = Field(2.0, ge=0.0, le=50.0)
    # Near clipping distance along the optical axis (m).
    near: float = Field(0.02, gt=0.0)
    # Added to the mipmap level (log2 texels per pixel): > 0 blurs, < 0 sharpens and aliases.
    mip_bias: float = 0.0
    # Cross-fade width between mipmap levels, in levels: 1 = trilinear, 0 = nearest level;
    # in between blends only near half-levels (fewer warps, no visible level seams).
    mip_blend: float = Field(0.5, ge=0.0, le=1.0)
    # Render this many times larger and average down (sensor area integration): sharper,
    # better anti-aliased, k^2 times slower.
    supersample: int = Field(1, ge=1, le=4)
    # Gaussian point-spread function of the optics (px): a real lens is never perfectly sharp,
    # and it anti-aliases silhouettes; symmetric, so it moves no corner. 0 = none.
    blur_sigma: float = Field(0.5, ge=0.0, le=5.0)


class VisibilityConf(StrictModel):
    """When a texture corner counts as observed in a view (its 2D-3D correspondence exists)."""

    # Projections closer than this to the image border are dropped (px).
    margin_px: float = Field(4.0, ge=0.0)
    # The corner's clean neighbourhood must span at least this many pixels along both axes.
    min_feature_px: float = Field(3.0, ge=0.0)
    # Angle between the surface normal and the direction to the camera, at most (degrees).
    max_obliquity_deg: float = Field(75.0, gt=0.0, lt=90.0)
    # Every pixel within this many pixels of the projection must show the corner's face.
    occlusion_margin_px: int = Field(2, ge=0, le=10)
    # Points seen by fewer mapping views are left out of the model.
    min_track_length: int = Field(2, ge=1)


class TrajectoryConf(StrictModel):
    kind: TrajectoryKind = "walk"
    n_frames: int = Field(300, ge=1)
    fps: float = Field(30.0, gt=0.0)
    # Where the orbit looks: at the room centre (and the walls beyond) or at the nearer walls.
    orbit_look: Literal["inward", "outward"] = "inward"


class SynthConf(StrictModel):
    seed: int = Field(0, ge=0)
    width: int = Field(640, ge=16)
    height: int = Field(480, ge=16)
    # Focal length in pixels; None: 525 scaled with the width (525 at 640 px).
    focal: float | None = Field(None, gt=0.0)
    mapping_views: int = Field(120, ge=2)
    scene: SceneConf = SceneConf()
    render: RenderConf = RenderConf()
    visibility: VisibilityConf = VisibilityConf()
    trajectory: TrajectoryConf = TrajectoryConf()


# Named presets: changes merged over ``SynthConf()``.
confs: dict[str, dict] = {
    "default": {},
    # A quick data set for smoke tests and demos.
    "small": {"mapping_views": 40, "trajectory": {"n_frames": 60}},
    # Noise-free images, e.g. to study pure geometry.
    "clean": {"render": {"noise_sigma": 0.0}},
    "flight": {"trajectory": {"kind": "flight"}},
    "orbit": {"trajectory": {"kind": "orbit"}},
}


def preset(name: str = "default", **changes) -> SynthConf:
    """The defaults with preset ``name`` and then ``changes`` merged over them."""
    if name not in confs:
        from ..errors import ConfigError

        raise ConfigError(f"unknown synth preset {name!r}; choose from {', '.join(confs)}")
    conf = merge_presets(SynthConf(), **confs[name])
    return merge_presets(conf, **changes) if changes else conf
