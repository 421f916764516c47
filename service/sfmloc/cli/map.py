"""sfmloc map inspect|verify: what a bundle holds, and whether it is intact."""

from __future__ import annotations

import argparse
import json


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "map", help="inspect or verify a map bundle", description="Inspect or verify a map bundle."
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
    v.add_argument("path", help="bundle folder")
    v.set_defaults(func=run_verify)


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
