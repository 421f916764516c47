"""sfmloc map inspect|verify|align|split: what a bundle holds, whether it is intact, putting it
in the user's frame, and splitting it into sub-maps."""

from __future__ import annotations

import argparse
import json
import sys


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "map",
        help="inspect, verify, align or split a map bundle",
        description="Inspect, verify, align or split a map bundle.",
    )
    msub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    i = msub.add_parser(
        "inspect",
        help="print a bundle's summary and verify its checksums",
        description="Print points, descriptors (per point), clusters, images, memory, build "
        "parameters and "
        "timings of a bundle, the map report (points per image, track lengths, coverage of each "
        "image, and "
        "a warning when the map is too sparse to localize against), and verify every array's "
        "checksum "
        "(exit 1 on corruption).",
    )
    i.add_argument("path", help="bundle folder")
    i.add_argument("--json", action="store_true", help="print the summary as JSON")
    i.set_defaults(func=run_inspect)
    v = msub.add_parser(
        "verify",
        help="check a bundle; exit non-zero on any corruption",
        description="Check the manifest, every array's presence, size, checksum, dtype and shape, "
        "the lookup "
        "tables' consistency and that the ANN index loads. Exit 0 when intact, 1 otherwise.",
    )
    v.add_argument("path", help="bundle folder (or a sub-map set folder: every part is checked)")
    v.set_defaults(func=run_verify)
    add_align_parser(msub)
    add_split_parser(msub)


def _load(path: str):
    from ..errors import BundleError
    from ..map.bundle import MapBundle, verify_bundle

    problems = verify_bundle(path)
    if problems:
        return None, problems
    try:
        return MapBundle(path, verify=False), []
    except BundleError as exc:
        return None, [str(exc)]


def run_inspect(args: argparse.Namespace) -> int:
    bundle, problems = _load(args.path)
    if bundle is None:
        for p in problems:
            print(f"CORRUPT: {p}")
        return 1
    from ..map.report import report_lines

    s = bundle.summary()
    s["report"] = bundle.report()
    s["checksums"] = "ok"
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    c = bundle.manifest.counts
    mem_per_m = s["memory_mb"] / max(c.descriptors, 1) * 1e6
    print(f"map          {s['name']}  ({s['path']})")
    print(
        f"build        {s['build_id']}  created {s['created_utc']}  source "
        f"{s['source'].get('kind', '?')}"
    )
    print(f"points       {c.points}")
    print(f"descriptors  {c.descriptors}  ({s['descriptors_per_point']} per point)")
    print(f"images       {c.images}  cameras {c.cameras}  observations {c.observations}")
    print(
        f"clusters     {c.clusters}  (mean "
        f"{sum(len(bundle.cluster_images(i)) for i in range(c.clusters)) / max(1, c.clusters):.1f} "
        "images each)"
    )
    print(
        f"index        {s['index']['kind']}, {s['index']['nlist']} lists, nprobe "
        f"{s['index']['nprobe']}"
    )
    print(
        f"memory       {s['memory_mb']} MB loaded ({mem_per_m:.0f} MB per million descriptors), "
        f"{s['disk_mb']} MB on disk"
    )
    t = s["timings_s"]
    if t:
        print("timings      " + ", ".join(f"{k} {v:.1f}s" for k, v in t.items()))
    p = s["params"]
    d = p.get("descriptors", {})
    if d:
        print(
            f"parameters   pyramid {d.get('octaves')} octaves x {d.get('per_octave')} "
            f"(+{d.get('up_levels', 0)} up), "
            f"tau {d.get('tau')} px, PCA {p.get('pca_dim')}, clusters max "
            f"{p.get('clusters', {}).get('max_size')} images"
        )
    for line in report_lines(s["report"]):
        print(line)
    print("checksums    ok")
    return 0


def run_verify(args: argparse.Namespace) -> int:
    from ..map.submaps import is_submap_set

    if is_submap_set(args.path):
        return _verify_set(args.path)
    bundle, problems = _load(args.path)
    if bundle is None:
        for p in problems:
            print(f"CORRUPT: {p}")
        return 1
    print(
        f"{args.path}: ok ({bundle.n_points} points, {bundle.n_descriptors} descriptors, build "
        f"{bundle.build_id})"
    )
    return 0


def _verify_set(path: str) -> int:
    from ..map.submaps import read_set_manifest, verify_submap_set

    problems = verify_submap_set(path)
    if problems:
        for p in problems:
            print(f"CORRUPT: {p}")
        return 1
    m = read_set_manifest(path)
    print(
        f"{path}: ok (sub-map set of {len(m.parts)} parts, {m.points} points, build {m.build_id})"
    )
    return 0


SPLIT_DESCRIPTION = """\
Split a map bundle into overlapping sub-maps for maps larger than memory (issue 14): each
sub-map is a complete bundle (its own ANN index) made of a group of the map's camera clusters,
plus the cameras within --overlap scene scales of them, and every point those cameras observe,
under the whole map's point ids. A small global index (camera centres and axes, part bounding
boxes and clusters, a place-recognition sample of descriptors) says which sub-maps a pose or a
query touches. Written atomically like a bundle, with checksums: 'sfmloc map verify OUT/NAME'
checks the set and every part. Give --parts K, or --max-points N (cut until each part holds at
most N points; a camera cluster is never cut).

The set is named after the bundle folder given (maps/campus -> maps/campus-submaps), not after
the name inside the bundle's manifest, and a server hosts it under that name ('sfmloc maps show
campus-submaps'): two copies of one build in different folders never write the same set.
--name chooses another.
"""


def add_split_parser(msub: argparse._SubParsersAction) -> None:
    sp = msub.add_parser(
        "split",
        help="split a bundle into overlapping sub-maps (out-of-core maps)",
        description=SPLIT_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sp.add_argument("path", metavar="FOLDER", help="bundle folder to split")
    how = sp.add_mutually_exclusive_group(required=True)
    how.add_argument("--parts", type=int, help="number of sub-maps")
    how.add_argument("--max-points", type=int, help="at most this many points per sub-map")
    sp.add_argument(
        "--out", default=None, help="folder to write the set into (default: beside the bundle)"
    )
    sp.add_argument(
        "--name", default=None, help="name of the set (default: FOLDER-submaps, FOLDER's own name)"
    )
    sp.add_argument(
        "--overlap",
        type=float,
        default=0.25,
        help="cameras within this many scene scales of a part's own cameras join it (0.25)",
    )
    sp.add_argument(
        "--vote-fraction",
        type=float,
        default=0.05,
        help="share of every image's descriptors in the global place-recognition sample (0.05)",
    )
    sp.set_defaults(func=run_split)


def run_split(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..errors import SfmlocError
    from ..map.submaps import split_bundle

    bundle, problems = _load(args.path)
    if bundle is None:
        for p in problems:
            print(f"CORRUPT: {p}", file=sys.stderr)
        return 1
    folder = Path(args.path).resolve()
    out = Path(args.out) if args.out else folder.parent
    # After the folder the user named (README: `map split maps/campus` then `maps show
    # campus-submaps`), not the manifest's name: a copied or renamed folder keeps its build's
    # name, and two copies of one build would write (and replace) the same set.
    name = args.name or f"{folder.name}-submaps"
    if args.name is None and folder.name != bundle.name:
        print(
            f"note: the set is named after the folder {folder.name!r}; the bundle inside calls "
            f"itself {bundle.name!r} (--name to choose)",
            file=sys.stderr,
        )
    try:
        path = split_bundle(
            bundle,
            out,
            name,
            parts=args.parts,
            max_points=args.max_points,
            overlap=args.overlap,
            vote_fraction=args.vote_fraction,
            progress=lambda msg: print(msg, file=sys.stderr, flush=True),
        )
    except SfmlocError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


ALIGN_DESCRIPTION = """\
Put a map in your frame: the least-squares similarity (scale, rotation, translation; Umeyama)
taking map coordinates onto known ones, applied to the whole bundle (points, camera poses; the
scene scale follows) and written atomically as a new build (new build id). On any failure the
old bundle stays as it was. Images-only maps have an arbitrary frame and scale: align them to a
few surveyed points, GNSS positions or known poses of some images.

Correspondences (one of, or --up alone):
  --positions FILE   'name x y z' lines: the known camera centre of map images (names matched
                     by file stem, e.g. frame-000020.color for frame-000020.color.jpg)
  --poses FILE       a COLMAP list 'name qw qx qy qz tx ty tz' or TUM file: the centres of the
                     poses of map images are used (orientations are not)
  --points FILE      'x y z X Y Z' lines: a point in map coordinates and in yours
At least 3 correspondences not on one line (2 with --up). Gravity: --up X Y Z is the map's up
direction in map coordinates (or 'cameras': the mean up of the map's cameras, for cameras held
level); the rotation then takes it exactly onto --up-target (default 0 0 1), and only the
rotation about that axis, the scale and the translation are fitted. --up without
correspondences only rotates the map.

Reported: the transform, the residuals on the given correspondences and, with --check FILE
(positions or poses, never used for the fit), on held-out images. --max-residual refuses to
write when a given correspondence is off by more than that (your units). Exit 0 when written
(or with --dry-run, computed), 1 when refused, 2 on bad input.
"""


def add_align_parser(msub: argparse._SubParsersAction) -> None:
    a = msub.add_parser(
        "align",
        help="transform a bundle into your frame (similarity from known positions/points, up)",
        description=ALIGN_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
        "  sfmloc map align maps/lab --positions surveyed.txt --check more_positions.txt\n"
        "  sfmloc map align maps/lab --points pairs.txt --up 0 -1 0 --out-name lab-metric\n"
        "  sfmloc map align maps/lab --up cameras        # gravity only: rotate, no scale",
    )
    a.add_argument("path", help="bundle folder")
    g = a.add_mutually_exclusive_group()
    g.add_argument("--positions", metavar="FILE", help="'name x y z' known camera centres")
    g.add_argument("--poses", metavar="FILE", help="known poses (COLMAP list or TUM): centres")
    g.add_argument("--points", metavar="FILE", help="'x y z X Y Z' point pairs (map, yours)")
    add_up_options(a)
    a.add_argument(
        "--no-scale", action="store_true", help="fit a rigid transform (scale 1: metric maps)"
    )
    a.add_argument(
        "--check",
        metavar="FILE",
        help="positions or poses of other map images: residuals reported, not fitted",
    )
    a.add_argument(
        "--max-residual",
        type=float,
        metavar="D",
        help="refuse (exit 1, nothing written) when a given correspondence is off by more than D",
    )
    a.add_argument(
        "--out-name",
        metavar="NAME",
        help="write the aligned bundle as NAME beside the original (default: replace it)",
    )
    a.add_argument("--dry-run", action="store_true", help="compute and report; write nothing")
    a.add_argument("--json", action="store_true", help="print the report as JSON")
    a.set_defaults(func=run_align)


def add_up_options(p: argparse.ArgumentParser) -> None:
    """--up / --up-target, shared with ``sfmloc build --align-*``."""
    p.add_argument(
        "--up",
        nargs="+",
        metavar="X",
        help="the map's up direction: 3 numbers in map coordinates, or 'cameras'",
    )
    p.add_argument(
        "--up-target",
        nargs=3,
        type=float,
        default=[0.0, 0.0, 1.0],
        metavar=("X", "Y", "Z"),
        help="where --up goes in your frame (default 0 0 1)",
    )


def _parse_up(values: list[str] | None, bundle) -> list[float] | None:
    from ..errors import InputError
    from ..map.align import cameras_up

    if values is None:
        return None
    if values == ["cameras"]:
        return [float(v) for v in cameras_up(bundle)]
    try:
        up = [float(v) for v in values]
    except ValueError:
        up = []
    if len(up) != 3:
        raise InputError(f"--up takes 3 numbers or 'cameras', got {' '.join(values)!r}")
    return up


def read_known_positions(path: str) -> dict:
    """Camera centres keyed by file stem from 'name x y z' lines or a pose file."""
    from pathlib import Path

    from ..errors import InputError
    from ..io.poses import read_poses
    from ..map.align import read_positions

    try:
        first = next(
            (ln.split() for ln in Path(path).read_text().splitlines() if ln.split("#")[0].strip()),
            [],
        )
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read {path}: {exc}") from None
    if len(first) == 4:
        return read_positions(path)
    return {k: T.center for k, T in read_poses(path).by_stem().items()}


def align_bundle_from_args(args: argparse.Namespace, path: str):
    """Compute the alignment the options ask for; returns (bundle, sim, report dict)."""
    import numpy as np

    from ..errors import InputError
    from ..map import align as A
    from ..map.bundle import MapBundle
    from ..transforms import rotvec_from_rotmat

    bundle = MapBundle(path)
    up = _parse_up(args.up, bundle)
    centers = A.image_centers(bundle)
    corr = None
    given = ""  # what corr holds, set with it
    if getattr(args, "points", None):
        corr = A.read_point_pairs(args.points)
        given = "points"
    elif getattr(args, "positions", None) or getattr(args, "poses", None):
        known = (
            A.read_positions(args.positions) if args.positions else read_known_positions(args.poses)
        )
        corr = A.match_positions(centers, known)
        given = "image positions"
    if corr is None:
        if up is None:
            raise InputError("give --positions, --poses or --points, or --up (gravity only)")
        sim = A.up_only(up, args.up_target)
    else:
        sim = A.estimate_sim3(
            corr, up_map=up, up_target=args.up_target, with_scale=not args.no_scale
        )
    report: dict = {
        "map": str(path),
        "from_build_id": bundle.build_id,
        "target_from_map": sim.to_dict(),
        "rotation_deg": float(np.degrees(np.linalg.norm(rotvec_from_rotmat(sim.rotation)))),
        "up_map": up,
        "up_target": list(args.up_target) if up is not None else None,
        "scene_scale": {"before": bundle.scene_scale, "after": bundle.scene_scale * sim.scale},
    }
    if corr is not None:
        report["given"] = _residual_report(A.residuals(sim, corr), corr.labels, given)
    if getattr(args, "check", None):
        known = read_known_positions(args.check)
        used = set(corr.labels) if corr is not None and given == "image positions" else set()
        # Only the map's images can be checked (a pose file of a whole sequence is fine).
        held = {k: v for k, v in known.items() if k not in used and k in centers}
        if not held:
            raise InputError(
                f"--check {args.check}: none of its images is a map image not used for the fit"
            )
        hc = A.match_positions(centers, held, "check file")
        report["held_out"] = _residual_report(A.residuals(sim, hc), hc.labels, "held-out images")
    return bundle, sim, report


def _residual_report(res, labels, what: str) -> dict:
    import numpy as np

    order = np.argsort(-res)
    return {
        "what": what,
        "count": int(len(res)),
        "median": float(np.median(res)),
        "rms": float(np.sqrt(np.mean(res**2))),
        "max": float(res.max()),
        "worst": [[labels[i], float(res[i])] for i in order[:5]],
        "all": {labels[i]: float(res[i]) for i in range(len(res))},
    }


def print_align_report(r: dict) -> None:
    s = r["target_from_map"]
    print(f"map          {r['map']}  (build {r['from_build_id']})")
    print(
        f"transform    scale {s['scale']:.6g}, rotation {r['rotation_deg']:.3f} deg, "
        f"quat_wxyz {[round(v, 6) for v in s['quat_wxyz']]}, "
        f"translation {[round(v, 6) for v in s['translation']]}"
    )
    if r["up_map"] is not None:
        print(f"up           map {[round(v, 4) for v in r['up_map']]} -> {r['up_target']} (exact)")
    sc = r["scene_scale"]
    print(f"scene scale  {sc['before']:.6g} -> {sc['after']:.6g}")
    for key in ("given", "held_out"):
        if key in r:
            g = r[key]
            worst = ", ".join(f"{n} {v:.4g}" for n, v in g["worst"][:3])
            print(
                f"residuals    {g['what']} ({g['count']}): median {g['median']:.4g}, rms "
                f"{g['rms']:.4g}, max {g['max']:.4g} (your units; worst: {worst})"
            )


def run_align(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..map.align import write_aligned
    from ..map.bundle import validate_name

    src = Path(args.path)
    name = validate_name(args.out_name) if args.out_name else src.name
    bundle, sim, report = align_bundle_from_args(args, args.path)
    refused = (
        args.max_residual is not None
        and "given" in report
        and report["given"]["max"] > args.max_residual
    )
    if not args.dry_run and not refused:
        record = {k: report[k] for k in ("up_map", "up_target") if report[k] is not None}
        if "given" in report:
            record["given"] = {k: report["given"][k] for k in ("what", "count", "rms", "max")}
        out = write_aligned(bundle, sim, src.parent, name, record=record)
        report["written"] = str(out)
        report["build_id"] = bundle_build_id(out)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print_align_report(report)
        if refused:
            print(
                f"REFUSED: a given correspondence is off by {report['given']['max']:.4g} > "
                f"--max-residual {args.max_residual:g}; nothing written"
            )
        elif args.dry_run:
            print("dry run: nothing written")
        else:
            print(f"written      {report['written']}  (build {report['build_id']})")
    return 1 if refused else 0


def bundle_build_id(path) -> str:
    from ..map.bundle import read_manifest

    return read_manifest(path).build_id
