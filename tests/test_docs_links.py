"""Code points at docs by section (`docs/method.md, "Decompositions in place"`): each named page
exists and has a heading or bold lead that starts with the named words, so a renamed section
cannot leave a comment pointing nowhere."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# `docs/page.md, "Section"` or `docs/page.md: "Section"`, possibly broken over comment lines.
LINK = re.compile(r"(docs/[a-z0-9-]+\.md)[,:]\s+\"([^\"]+)\"")


def sections(page: Path) -> list[str]:
    text = page.read_text()
    heads = [m.group(1) for m in re.finditer(r"^#+\s+(.+)$", text, re.M)]
    leads = [m.group(1) for m in re.finditer(r"\*\*([^*]+)\*\*", text)]
    return [re.sub(r"\s+", " ", s).strip().rstrip(".").lower() for s in heads + leads]


def code_links() -> list[tuple[str, str, str]]:
    where = ["kgs_core", "backend", "app", "frontend", "scripts"]
    files = subprocess.run(["git", "ls-files", *where], cwd=ROOT, capture_output=True, text=True).stdout.split()
    files = [f for f in files if f.endswith((".py", ".js"))]
    out = []
    for name in files:
        text = (ROOT / name).read_text()
        # Comment continuation lines joined, so that a section name broken over lines reads whole.
        joined = re.sub(r"\s*\n\s*(#|//)?\s*", " ", text)
        out += [(name, page, re.sub(r"\s+", " ", title)) for page, title in LINK.findall(joined)]
    return out


def test_every_docs_section_the_code_names_exists():
    links = code_links()
    assert len(links) > 20  # the pattern still finds the links
    missing = []
    for name, page, title in links:
        path = ROOT / page
        want = title.rstrip(".").lower()
        if not path.is_file() or not any(s.startswith(want) for s in sections(path)):
            missing.append(f'{name}: {page}, "{title}"')
    assert not missing, "sections named in code but not in the docs:\n" + "\n".join(sorted(set(missing)))
