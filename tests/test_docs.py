"""README and its records in docs/: every link and every citation finds its record, and every
record keeps its parts.

docs/beyond-the-paper.md holds the rows of README's "Beyond the paper" table (up to 7,500
characters a cell), read by everyone before trying an idea; docs/measurements.md the measurement
logs that were README's paragraphs (Throughput, Status, Reliability, ...: up to 13,000
characters each), docs/development.md the make targets' details. README gives the user part in
short and links to each record; code comments cite them as ``docs/FILE.md#ANCHOR``. A link or a
citation that names no record sends the reader nowhere, and nothing else notices it."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
RECORDS = REPO / "docs" / "beyond-the-paper.md"
RECORDS_NAME = "docs/beyond-the-paper.md"
# The record groups, by their section anchors (README links to each group).
BEHAVIOUR, SAME_RESULTS, NOT_TAKEN = "behaviour-changes", "same-results", "measured-not-taken"
ANCHOR = re.compile(r'<a id="([^"]+)"></a>\n')


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(text: str) -> list[str]:
    """The anchors a Markdown file defines: explicit ``<a id>`` and its headings' slugs
    (outside fenced blocks, where a ``#`` line is no heading)."""
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    headings = re.findall(r"^#{1,6} (.+)$", prose, re.M)
    return ANCHOR.findall(prose) + [_slug(h) for h in headings]


def _records() -> dict[str, tuple[str, str]]:
    """Each record's anchor -> (its group's anchor, its text up to the next anchor)."""
    text = re.sub(r"```.*?```", "", RECORDS.read_text(), flags=re.S)
    parts = ANCHOR.split(text)
    records: dict[str, tuple[str, str]] = {}
    group = ""
    for anchor, body in zip(parts[1::2], parts[2::2]):
        if body.startswith("## "):
            group = anchor
        elif body.startswith("### "):
            records[anchor] = (group, body)
    return records


def _links(text: str, target: str) -> list[str]:
    """The anchors of the Markdown links and plain citations of ``target#anchor`` in text."""
    return re.findall(re.escape(target) + r"#([A-Za-z0-9_-]+)", text)


def test_records_anchors_are_unique_and_grouped():
    # Explicit anchors and heading slugs apart: a group's anchor is its own heading's slug.
    text = re.sub(r"```.*?```", "", RECORDS.read_text(), flags=re.S)
    for anchors in (ANCHOR.findall(text), [_slug(h) for h in re.findall(r"^#+ (.+)$", text, re.M)]):
        assert len(anchors) == len(set(anchors)), {a for a in anchors if anchors.count(a) > 1}
    groups = {group for group, _ in _records().values()}
    assert groups == {BEHAVIOUR, SAME_RESULTS, NOT_TAKEN}, groups


def test_every_record_has_change_why_and_switch():
    for anchor, (_, body) in _records().items():
        for part in ("**Change:** ", "**Why (measured):** ", "**Switch:** "):
            assert f"\n{part}" in body, f"record {anchor} has no {part.strip()}"


def test_every_record_is_in_the_contents():
    text = RECORDS.read_text()
    contents = text.split("## Contents", 1)[1].split('<a id="', 1)[0]
    listed = re.findall(r"\]\(#([A-Za-z0-9_-]+)\)", contents)
    assert sorted(set(listed) - {BEHAVIOUR, SAME_RESULTS, NOT_TAKEN}) == sorted(_records())
    # "[Behaviour changes with a switch](#behaviour-changes) (44):": each group's count is its own
    # (two branches that each add a record both write the same count; a merge keeps it stale).
    for group in (BEHAVIOUR, SAME_RESULTS, NOT_TAKEN):
        said = re.findall(rf"\]\(#{group}\) \((\d+)\):", contents)
        count = sum(1 for g, _ in _records().values() if g == group)
        assert said == [str(count)], f"contents: {said} records of {group}, not {count}"


def test_readme_links_find_their_records():
    """Every README link into the records names one, and README's table links every behaviour
    change (a record in that group without a row is a change a README reader never sees)."""
    readme = README.read_text()
    linked = _links(readme, RECORDS_NAME)
    assert linked, "README links to no record"
    missing = sorted(set(linked) - set(_anchors(RECORDS.read_text())))
    assert not missing, f"README links to anchors {RECORDS_NAME} does not define: {missing}"
    section = readme.split("\n## Beyond the paper\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| [")]
    in_table = [a for row in rows for a in _links(row.split(" | ", 1)[0], RECORDS_NAME)]
    behaviour = sorted(a for a, (g, _) in _records().items() if g == BEHAVIOUR)
    assert sorted(in_table) == behaviour
    for group in (SAME_RESULTS, NOT_TAKEN):
        # "([13 records](docs/beyond-the-paper.md#same-results))": the count is the group's.
        said = re.findall(rf"\[(\d+) records\]\({re.escape(RECORDS_NAME)}#{group}\)", section)
        count = sum(1 for g, _ in _records().values() if g == group)
        assert said == [str(count)], f"README says {said} records of {group}; there are {count}"


def test_records_links_resolve():
    """The records' own links: within the file, and back to README's sections."""
    text = RECORDS.read_text()
    own = set(_anchors(text))
    inner = re.findall(r"\]\(#([A-Za-z0-9_-]+)\)", text)
    assert sorted(set(inner) - own) == []
    to_readme = _links(text, "../README.md")
    assert to_readme and not set(to_readme) - set(_anchors(README.read_text()))


# The records moved out of README's paragraphs: one record per paragraph, each linked from the
# README text it was cut from.
PARAGRAPH_RECORDS = ("measurements.md", "development.md")
DOC_LINK = re.compile(r"docs/([A-Za-z0-9_.-]+\.md)#([A-Za-z0-9_-]+)")


def _doc_anchors(name: str) -> set[str]:
    path = REPO / "docs" / name
    assert path.is_file(), f"docs/{name} is cited but does not exist"
    return set(_anchors(path.read_text()))


def _paragraph_records(name: str) -> dict[str, str]:
    """A paragraph-records file's records: anchor -> its text up to the next anchor."""
    parts = ANCHOR.split((REPO / "docs" / name).read_text())
    return {a: body for a, body in zip(parts[1::2], parts[2::2]) if body.startswith("### ")}


def test_paragraph_records_are_unique_listed_linked_and_point_back():
    """Each record of docs/measurements.md and docs/development.md: its anchor is unique, it
    is in the file's contents, README links to it (a record nothing links to is a measurement
    no reader finds from the text it backs), and it names the README section it came from."""
    readme = README.read_text()
    readme_anchors = set(_anchors(readme))
    for name in PARAGRAPH_RECORDS:
        text = (REPO / "docs" / name).read_text()
        anchors = ANCHOR.findall(text)
        assert len(anchors) == len(set(anchors)), {a for a in anchors if anchors.count(a) > 1}
        records = _paragraph_records(name)
        assert records, f"docs/{name} has no records"
        contents = text.split("## Contents", 1)[1].split('<a id="', 1)[0]
        assert sorted(re.findall(r"\]\(#([A-Za-z0-9_-]+)\)", contents)) == sorted(records)
        linked = set(_links(readme, f"docs/{name}"))
        assert not set(records) - linked, f"README links to no {sorted(set(records) - linked)}"
        for anchor, body in records.items():
            back = _links(body.split("\n\n", 2)[1], "../README.md")
            assert back, f"docs/{name}#{anchor} names no README section"
            assert set(back) <= readme_anchors, f"docs/{name}#{anchor}: {back} not in README"


def test_readme_links_into_docs_resolve():
    """Every ``docs/FILE.md#ANCHOR`` README names (links and text) is a file with that anchor."""
    readme = README.read_text()
    cited = DOC_LINK.findall(readme)
    assert {name for name, _ in cited} >= {"beyond-the-paper.md", *PARAGRAPH_RECORDS}
    missing = sorted(f"docs/{n}#{a}" for n, a in set(cited) if a not in _doc_anchors(n))
    assert not missing, f"README names anchors that do not exist: {missing}"
    for name in re.findall(r"\]\(docs/([A-Za-z0-9_.-]+)\)", readme):
        assert (REPO / "docs" / name).is_file(), f"README links to docs/{name}, which is missing"


def test_docs_links_to_each_other_resolve():
    """A docs file's links to another (``](measurements.md#status-rules)``) find their anchor."""
    for path in sorted((REPO / "docs").glob("*.md")):
        for name, anchor in re.findall(
            r"\]\(([A-Za-z0-9_-]+\.md)#([A-Za-z0-9_-]+)\)", path.read_text()
        ):
            assert anchor in _doc_anchors(name), f"{path.name} links to {name}#{anchor}"


def test_code_citations_find_their_records():
    """A comment or docstring citing ``docs/FILE.md#ANCHOR`` (what a measured default points
    its reader to) names a record that exists, in any docs file."""
    cited: dict[str, list[str]] = {}
    for root in ("service", "client", "tests"):
        for path in sorted((REPO / root).rglob("*.py")):
            if path == Path(__file__).resolve():
                continue  # its docstrings name the form, not a record
            for name, anchor in DOC_LINK.findall(path.read_text()):
                cited.setdefault(f"docs/{name}#{anchor}", []).append(str(path.relative_to(REPO)))
    assert any(c.startswith("docs/measurements.md#") for c in cited), "no code cites a measurement"
    missing = {
        c: paths
        for c, paths in cited.items()
        if c.split("#")[1] not in _doc_anchors(c.split("/", 1)[1].split("#")[0])
    }
    assert not missing, missing


def test_code_citations_of_readme_name_its_sections():
    """``README, Conventions`` / ``README, Zenoh`` in code: the name starts a README heading or
    a bold list item or paragraph (the promise it cites must still be in README, not only in a
    record)."""
    readme = README.read_text()
    names = re.findall(r"^#{1,6} (.+)$", readme, re.M)
    names += re.findall(r"^(?:- )?\*\*([^*]+)\*\*", readme, re.M)
    cited: dict[str, list[str]] = {}
    for root in ("service", "client", "tests"):
        for path in sorted((REPO / root).rglob("*.py")):
            if path == Path(__file__).resolve():
                continue
            text = " ".join(path.read_text().split())  # a citation may wrap
            for name in re.findall(r"README, ([A-Z][A-Za-z0-9 ]*[A-Za-z0-9])", text):
                cited.setdefault(name, []).append(str(path.relative_to(REPO)))
    assert cited, "no code cites a README section"
    missing = {n: p for n, p in cited.items() if not any(h.startswith(n) for h in names)}
    assert not missing, f"code cites README sections that do not exist: {missing}"


# README's switch column gives each knob's default as `Conf.field` = value (a bare `field` after
# it belongs to the same class); these are the classes it names.
def _switch_classes() -> dict[str, object]:
    from sfmloc.builder.descriptors import DescriptorConf
    from sfmloc.builder.harris_points import HarrisPointsConf
    from sfmloc.builder.refine import RefineConf
    from sfmloc.builder.sfm.conf import SfmConf
    from sfmloc.engine import EngineConf
    from sfmloc.server.config import ZenohConf

    return {
        "EngineConf": EngineConf(),
        "DescriptorConf": DescriptorConf(),
        "RefineConf": RefineConf(),
        "HarrisPointsConf": HarrisPointsConf(),
        "SfmConf": SfmConf(),
        "zenoh": ZenohConf(),
    }


# The build presets' section of BuildConf each builder class sits in.
BUILD_SECTIONS = {
    "DescriptorConf": "descriptors",
    "RefineConf": "refine",
    "HarrisPointsConf": "harris_points",
}
SWITCH = re.compile(r"`(?:(\w+)\.)?(\w+)`(?: = (`[^`]*`|[^\s,()]+))?")


def _same(written: str, value: object) -> bool:
    """Whether a table's written value (`name`, true, 0.02, 640) is the code's ``value``."""
    if written.startswith("`"):
        return written.strip("`") == value
    if isinstance(value, bool):
        return written in ("true", "false") and (written == "true") == value
    try:
        return float(written) == float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return written == str(value)


def _switch_cells() -> list[tuple[str, str]]:
    """(the record's anchor, the switch cell) of each row of README's table."""
    section = README.read_text().split("\n## Beyond the paper\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| [")]
    return [(_links(r, RECORDS_NAME)[0], r.rstrip(" |").rsplit(" | ", 1)[1]) for r in rows]


def test_readme_switches_name_the_codes_knobs_and_defaults():
    """Each `Conf.field` in README's switch column is a knob of that class, and its written
    default (`Conf.field` = value) is the code's: a default changed in the code and not in the
    table (or a knob renamed) would send a reader to the wrong setting."""
    import inspect

    from sfmloc.builder.build import PRESETS, preset
    from sfmloc_client.placement import Placement

    classes = _switch_classes()
    checked = 0
    wrong = []
    for anchor, cell in _switch_cells():
        owner = "EngineConf"  # a cell naming no class names EngineConf's knobs
        # the knobs and their defaults; parentheses hold the off values and presets
        # (a call such as `Placement(late_timeout=5.0)` is read below)
        knobs = re.sub(r"\([^()]*\)", "", re.sub(r"`\w+\([^`]*\)`", "", cell))
        for cls, field, written in SWITCH.findall(knobs):
            if cls:
                if cls not in classes:
                    wrong.append(f"{anchor}: {cls}.{field}: no class this test knows")
                    continue
                owner = cls
            conf = classes[owner]
            if not hasattr(conf, field):
                wrong.append(f"{anchor}: {owner}.{field} is no knob")
                continue
            if written and not _same(written, getattr(conf, field)):
                wrong.append(
                    f"{anchor}: {owner}.{field} = {written}, the code's is {getattr(conf, field)!r}"
                )
            checked += bool(written)
        # "(presets `default`, `dense`: on; `paper`, `fast`: off)" of a builder knob
        for names, state in re.findall(r"presets? ((?:`\w+`(?:, )?)+): (on|off)", cell):
            for name in re.findall(r"`(\w+)`", names):
                assert name in PRESETS, f"{anchor}: no build preset {name}"
                field = re.match(r"`(\w+)\.(\w+)`", cell)
                assert field and field.group(1) in BUILD_SECTIONS, anchor
                value = getattr(
                    getattr(preset(name), BUILD_SECTIONS[field.group(1)]), field.group(2)
                )
                if value != (state == "on"):
                    wrong.append(f"{anchor}: preset {name} has {field.group(2)} {value}")
        for cls, arg, written in re.findall(r"`(\w+)\((\w+)=([^)]+)\)`", cell):
            assert cls == "Placement", f"{anchor}: {cls} is not a class this test knows"
            default = inspect.signature(Placement).parameters[arg].default
            if not _same(written, default):
                wrong.append(f"{anchor}: {cls}({arg}={written}), the code's is {default!r}")
            checked += 1
    assert not wrong, wrong
    assert checked >= 60, f"only {checked} defaults read: has the table's form changed?"
