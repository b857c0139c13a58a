"""The README is a front door: short, its links resolve, and every number of its speed and accuracy tables is
one a results file under bench/results/ holds. (Its Python snippet runs as printed in
tests/test_docs_snippets.py, with every snippet of the documentation site.) The scene reference of the docs
is a valid scene."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)]*)?\)")


def test_readme_is_a_front_door():
    """At most 250 lines, and it keeps the parts a new user looks for: set-up, tests, the API, the command
    line, speed, accuracy and the way into the manual."""
    text = README.read_text()
    assert len(text.split("\n")) <= 250
    for heading in ("## Set up and run", "## The Python API", "## Command line", "## Speed", "## Accuracy",
                    "## Documentation"):
        assert heading in text, heading
    assert "python -m pytest -q" in text and "2-core" in text


def test_links_resolve():
    """Every relative link of the README and of the docs pages names a file that exists (the site's build
    checks its own pages again with ``mkdocs build --strict``; this also covers the README)."""
    pages = [README, *sorted((ROOT / "docs").glob("*.md")), ROOT / "bench" / "README.md", ROOT / "bench" / "RESULTS.md",
             *sorted((ROOT / "bench" / "results").glob("*.md"))]
    for page in pages:
        for target, _ in LINK.findall(page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            assert (page.parent / target).exists(), f"{page.name}: a link to {target}, which does not exist"


def test_bench_index_names_every_script():
    """bench/README.md has a row for every bench script, with a command that runs it and a results file (or says
    it has none); bench/RESULTS.md sends every section number the code cites to an existing topic file."""
    index = (ROOT / "bench" / "README.md").read_text()
    rows = {row[0].strip("`"): row for row in table_after(index, "| script |")}
    scripts = sorted(p.name for p in (ROOT / "bench").glob("*.py"))
    assert sorted(rows) == scripts
    for name, (_, what, command, results) in rows.items():
        assert f"python bench/{name}" in command, name
        assert "results/" in results or results.startswith("none"), name
    sections = (ROOT / "bench" / "RESULTS.md").read_text()
    for path in ROOT.glob("warpspring/**/*.py"):
        for cited in re.findall(r"RESULTS\.md``? §(\d+[a-z]?)", path.read_text()):
            assert f"| §{cited} |" in sections, f"{path.name} cites §{cited}"


def test_every_results_table_names_its_device_versions_and_date():
    """In each topic file of bench/results/ (those bench/README.md links), the text between a table and the one
    before it (or the file's start) names the device, the Warp version and the date the table was measured on."""
    index = (ROOT / "bench" / "README.md").read_text()
    topics = sorted(set(re.findall(r"\]\(results/(\w+\.md)\)", index)))
    assert {"cloth.md", "trade.md", "guard.md", "selfcontact.md", "cloth_materials.md"} <= set(topics)
    checks = {"device": r"H100|H200|CPU|VM|host", "Warp version": r"Warp\s+\d", "date": r"20\d\d-\d\d-\d\d"}
    for name in topics:
        lines = (ROOT / "bench" / "results" / name).read_text().split("\n")
        context: list[str] = []
        previous_was_table = False
        for number, line in enumerate(lines, 1):
            is_table = line.startswith("|")
            if is_table and not previous_was_table:
                text = "\n".join(context)
                missing = [what for what, pattern in checks.items() if not re.search(pattern, text)]
                assert not missing, f"bench/results/{name}:{number}: the table does not say its {', '.join(missing)}"
                context = []
            elif not is_table:
                context.append(line)
            previous_was_table = is_table


def table_after(text: str, marker: str) -> list[list[str]]:
    """The rows (cells) of the first markdown table after ``marker``, header and rule left out."""
    lines = text[text.index(marker):].split("\n")
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip("|").split("|")])
    return rows


def test_cited_numbers_come_from_results_files():
    """Each number the README's speed and accuracy tables cite appears, as written, in the results file the
    section names: no number is rounded differently from its measurement or made up."""
    text = README.read_text()
    for section, results in (("## Speed", "guard_cost.md"), ("## Accuracy", "trade.md")):
        body = text[text.index(section):]
        assert f"bench/results/{results}" in body.split("\n## ")[0]
        measured = (ROOT / "bench" / "results" / results).read_text()
        rows = table_after(text, section)
        assert rows
        cited = 0
        for row in rows:
            for cell in row[1:]:  # the first column names the row
                value = cell.replace("*", "").strip()
                if not value or not re.search(r"\d", value):
                    continue
                assert value in measured, f"README {section}: {value!r} is not in bench/results/{results}"
                cited += 1
        assert cited >= 2 * len(rows)


def test_scene_reference_parses_and_builds():
    """The docs' scene-file reference is a valid format-2 scene: it parses, and its model has the pin group and
    the stabiliser it describes."""
    from warpspring.io.scene import parse_scene, tomllib  # tomllib, or tomli on Python 3.10

    page = ROOT / "docs" / "scenes.md"
    text = re.search(r"```toml\n(.*?)```", page.read_text(), re.S).group(1)
    scene = parse_scene(tomllib.loads(text), path=str(ROOT / "reference.toml"))  # saved at the root, as it says
    assert scene.version == 2 and scene.guard.tear_strain == 10.0
    model = scene.builder().finalize("cpu")
    assert [g.name for g in model.pin_groups.groups] == ["edge"]
    assert model.stabilizers.max_strain == 0.1
    assert [c.kind for c in model.shapes] == ["plane", "box"] and model.shapes[1].moving
    contacts = scene.finalize("cpu")  # with the [contacts] options
    assert contacts.contact_slots == 3 and contacts.contact_stage
