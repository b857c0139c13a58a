"""Every Python snippet of the README and of the documentation site runs exactly as printed.

The convention the pages follow (``docs/index.md`` states it for writers):

- a fenced block whose info string is ``python`` is a snippet and runs; shell commands are ``bash``, outputs
  ``text`` and scene files ``toml``, none of which run here;
- a snippet runs on its own, in a fresh namespace, unless the line before its fence is the comment
  ``<!-- continues the previous snippet -->``: then it runs in the namespace the page's previous snippet left.

Each chain runs verbatim (no edit of its text) in a temporary folder that holds a link to ``examples/``, so a
snippet reads ``examples/meshes/...`` as it would from the repository's root and writes its files into the
folder. Snippets choose their own device (CUDA where present, else the CPU) and are sized to run on the CPU
in a minute all together.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
CONTINUES = "<!-- continues the previous snippet -->"
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```\s*$", re.S | re.M)


def snippet_chains(path: Path) -> list[tuple[int, list[str]]]:
    """The page's Python snippets grouped into chains: (line of the chain's first snippet, [code, ...])."""
    text = path.read_text()
    chains: list[tuple[int, list[str]]] = []
    for match in FENCE.finditer(text):
        if match.group(1) != "python":
            continue
        before = text[: match.start()].rstrip("\n").rsplit("\n", 1)[-1].strip()
        if before == CONTINUES:
            assert chains, f"{path.name}: a snippet continues, but no snippet comes before it"
            chains[-1][1].append(match.group(2))
        else:
            chains.append((text.count("\n", 0, match.start()) + 1, [match.group(2)]))
    return chains


CHAINS = [(page, line, codes) for page in PAGES for line, codes in snippet_chains(page)]


def test_every_page_is_scanned_and_fences_close():
    """The pages with snippets are found, and every fence of every page closes (an odd count of fences would
    make the scan above skip code silently)."""
    assert {page.name for page, _, _ in CHAINS} >= {"README.md", "getting-started.md"}
    for page in PAGES:
        fences = [line for line in page.read_text().split("\n") if line.startswith("```")]
        assert len(fences) % 2 == 0, f"{page.name}: an unclosed code fence"


@pytest.mark.parametrize("page, line, codes", CHAINS,
                         ids=[f"{page.name}:{line}" for page, line, _ in CHAINS])
def test_snippet_runs_as_printed(page, line, codes, tmp_path, monkeypatch):
    """The chain of snippets that starts at ``page:line`` runs verbatim, one snippet after the other in one
    namespace, and picks its own device."""
    assert 'device = "cuda:0" if wp.is_cuda_available() else "cpu"' in codes[0] or "finalize(" not in "".join(codes)
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__snippet__"}
    for k, code in enumerate(codes):
        exec(compile(code, f"{page}:{line} (snippet {k + 1})", "exec"), namespace)
