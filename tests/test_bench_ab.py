"""The same-run A/B tool (``python -m sfmloc.bench.ab``) on the synthetic world: variants that
must give the same poses are found identical, a variant that changes the detector is not, and
bad variant specs are named."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import sfmloc
from sfmloc.bench import ab
from sfmloc.errors import InputError

TREE = Path(sfmloc.__file__).resolve().parents[2]  # the checkout these tests import


def test_ab_finds_identical_and_different_variants(world, tmp_path, capsys):
    synth = world.root / "synth"
    fewer = tmp_path / "fewer.json"
    fewer.write_text(json.dumps({"gamma": 0.05}))  # a much higher Harris threshold
    same = tmp_path / "same.json"
    same.write_text("{}")
    copy = tmp_path / "room-copy"  # another bundle folder for one variant (--map)
    shutil.copytree(world.maps_dir / "room", copy)
    out = tmp_path / "ab.json"
    rc = ab.main(
        [
            str(world.maps_dir / "room"),
            str(synth / "video"),
            "--camera",
            str(synth / "camera.json"),
            "--groundtruth",
            str(synth / "video_poses.txt"),
            "--max-frames",
            "12",
            "--reps",
            "1",
            "--variant",
            f"base={TREE}",
            "--variant",
            f"same={TREE}",
            "--variant",
            f"fewer={TREE}",
            "--variant",
            f"copy={TREE}",
            "--map",
            f"copy={copy}",
            "--config",
            f"same={same}",
            "--config",
            f"fewer={fewer}",
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())["variants"]
    assert set(doc) == {"base", "same", "fewer", "copy"}
    assert doc["copy"]["map"] == str(copy.resolve()) and doc["base"]["map"] is None
    assert doc["copy"]["vs_base"]["identical_poses"] == 1.0  # the same map in another folder
    assert all(v["cpu_recorded"] for v in doc.values())
    assert doc["same"]["vs_base"]["on"] == "cpu"
    assert doc["same"]["vs_base"]["identical_poses"] == 1.0
    assert doc["same"]["vs_base"]["max_centre_distance"] == 0.0
    assert doc["fewer"]["vs_base"]["identical_poses"] < 1.0
    assert doc["base"]["ms_mean"] > 0 and doc["same"]["vs_base"]["mean_ratio"] > 0
    assert "localized 12/12" in doc["base"]["accuracy"]
    text = capsys.readouterr().out
    assert "vs base (cpu)" in text and "identical poses 100.0%" in text
    assert "map room-copy, CPU" in text
    # the stages in CPU time too: each at most its wall time, and they add up to the frame's
    cpu, wall = doc["base"]["stages_cpu_ms"], doc["base"]["stages_ms"]
    assert set(cpu) == set(wall) and cpu["total"] > 0
    assert all(cpu[k] <= 1.01 * wall[k] + 0.05 for k in cpu)  # (means over the frames)
    assert sum(v for k, v in cpu.items() if k != "total") == pytest.approx(cpu["total"], rel=0.03)
    assert "stages (CPU ms/frame): detect" in text


def test_ab_compares_each_variant_s_repetitions_with_its_first():
    """With two or more repetitions each variant's later runs are compared with its first
    (the engine is repeatable: below 100% is a fault, named in the report). The runs here
    are the dicts ``run_once`` returns; the first variant repeats itself, the second moves a
    pose by 0.5 units in its third run."""

    def run(traj: dict) -> dict:
        ms = np.array([10.0, 12.0])
        summary = {"frames": 2, "localized_frames": 2, "median_position_error_m": 0.01}
        return {"summary": summary, "ms": ms, "latency": ms, "cpu": True, "traj": traj}

    c = np.zeros(3)
    same = {"f0": ("0 0 0 0 0 0 0 1", c), "f1": ("1 0 0 0 0 0 0 1", c + 1)}
    moved = {**same, "f1": ("1 0.5 0 0 0 0 0 1", c + [1.5, 1, 1])}
    a = ab.Variant("a", TREE, runs=[run(same), run(same), run(same)])
    b = ab.Variant("b", TREE, runs=[run(same), run(same), run(moved)])
    result = ab.compare([a, b])
    assert result["a"]["repeats"] == {"identical_poses": 1.0, "max_centre_distance": 0.0}
    assert result["b"]["repeats"] == {"identical_poses": 0.5, "max_centre_distance": 0.5}
    assert result["b"]["vs_base"]["identical_poses"] == 1.0  # the first runs agree
    text = ab.format_report(result, "1 1 1", "1 1 1", 3)
    assert "repeats against its first run: identical poses 100.0%" in text
    assert "repeats against its first run: identical poses 50.0% (the least of them)" in text
    single = ab.compare([ab.Variant("a", TREE, runs=[run(same)]), b])
    assert "repeats" not in single["a"]  # one run: nothing to compare


def test_ab_fps_sets_the_replay_clock_and_the_default_stays_30(world, tmp_path, capsys):
    """--fps HZ reaches the engine: the replay's per-frame stamps (the ones ``localize`` gets)
    are index / HZ; without it they are index / 30, as before."""
    synth = world.root / "synth"
    base = [str(world.maps_dir / "room"), str(synth / "video")]
    base += ["--camera", str(synth / "camera.json"), "--max-frames", "4", "--start", "2"]
    stamps = {}
    for label, extra in (("default", []), ("10", ["--fps", "10"]), ("3", ["--fps", "3"])):
        args = ab.build_parser().parse_args([*base, *extra])
        work = tmp_path / label
        work.mkdir()
        run = ab.run_once(ab.Variant("v", TREE), args, work, 0)
        stamps[label] = [f["stamp"] for f in run["summary"]["per_frame"]]
        assert run["summary"]["clock_fps"] == pytest.approx(float(label) if extra else 30.0)
        # (the trajectory writes stamps to 6 decimals)
        assert sorted(float(t) for t in run["traj"]) == pytest.approx(stamps[label], abs=1e-6)
    assert stamps["default"] == pytest.approx([i / 30 for i in range(2, 6)])
    assert stamps["10"] == pytest.approx([i / 10 for i in range(2, 6)])
    assert stamps["3"] == pytest.approx([i / 3 for i in range(2, 6)])
    # and through main: the report names the clock; a non-positive rate is refused
    args = [*base, "--reps", "1", "--variant", f"a={TREE}", "--variant", f"b={TREE}"]
    assert ab.main([*args, "--fps", "10"]) == 0
    assert "replay clock 10 frames/s" in capsys.readouterr().out
    assert ab.main([*args, "--fps", "0"]) == 2
    assert "--fps must be positive" in capsys.readouterr().err


def test_ab_replays_a_variant_s_own_map(world, tmp_path, capsys):
    """A variant's --map is the bundle it replays: a folder whose arrays are missing fails
    that variant's replay, named."""
    broken = tmp_path / "broken"
    broken.mkdir()
    shutil.copy(world.maps_dir / "room" / "manifest.json", broken / "manifest.json")
    synth = world.root / "synth"
    args = [str(world.maps_dir / "room"), str(synth / "video")]
    args += ["--camera", str(synth / "camera.json"), "--max-frames", "2", "--reps", "1"]
    args += ["--variant", f"base={TREE}", "--variant", f"other={TREE}", "--map", f"other={broken}"]
    assert ab.main(args) == 2
    assert "variant other: sfmloc replay failed" in capsys.readouterr().err


def test_ab_names_bad_variants(tmp_path):
    with pytest.raises(InputError, match="NAME=TREE"):
        ab.parse_variants(["base"], [])
    with pytest.raises(InputError, match="not a checkout"):
        ab.parse_variants([f"a={tmp_path}", f"b={TREE}"], [])
    with pytest.raises(InputError, match="at least two"):
        ab.parse_variants([f"a={TREE}"], [])
    with pytest.raises(InputError, match="given twice"):
        ab.parse_variants([f"a={TREE}", f"a={TREE}"], [])
    with pytest.raises(InputError, match="named variant"):
        ab.parse_variants([f"a={TREE}", f"b={TREE}"], [f"c={tmp_path}"])
    with pytest.raises(InputError, match="not found"):
        ab.parse_variants([f"a={TREE}", f"b={TREE}"], [f"b={tmp_path / 'none.json'}"])
    with pytest.raises(InputError, match="not a map bundle"):
        ab.parse_variants([f"a={TREE}", f"b={TREE}"], [], [f"b={tmp_path}"])
    with pytest.raises(InputError, match="NAME=BUNDLE for a named variant"):
        ab.parse_variants([f"a={TREE}", f"b={TREE}"], [], [f"c={tmp_path}"])


def test_the_readme_ab_command_parses():
    """README's `python -m sfmloc.bench.ab MAP FRAMES ...` lines (not the elided `...` ones)
    parse as written: README gave it without the required --camera."""
    import re
    import shlex

    text = (TREE / "README.md").read_text()
    spans = re.findall(r"`python -m sfmloc\.bench\.ab ([^`]+)`", text)
    lines = [s for s in spans if "..." not in s]
    assert lines, "README shows how to run sfmloc.bench.ab"
    for line in lines:
        args = ab.build_parser().parse_args(shlex.split(line))  # exits 2 on a bad line
        assert len(args.variant) >= 2, line
