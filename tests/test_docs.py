"""Every file a docstring or comment of the package names exists, and every link of the docs resolves.

A reference is a word ending in ``.md`` or ``.py`` (``docs/PHYSICS.md``, ``physics/so3.py``,
``joints.py``) in a docstring (any string statement: module, class, function or attribute docstring)
or a comment of ``src/tracegs/**/*.py``. It names an existing file when the path, taken relative to
one of these folders, is a file: the repository root, the package (``src/tracegs``), ``docs/``, or the
folder of the module that cites it. A path with a ``NAME`` part (``docs/results/NAME.md``) is a
pattern, not a file, and is skipped. Nothing else is excused: a reference to a file outside the
repository (METHOD.md) fails; cite the TRACE paper's section or equation instead.

A link of README.md, benchmarks/README.md, docs/*.md and docs/results/*.md (``[text](target)``) that
is not a URL or an anchor names a file or folder relative to the page that holds it.
"""

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "src" / "tracegs"
REFERENCE = re.compile(r"(?<![\w./-])((?:\.\./|\./)?[\w-][\w./-]*\.(?:md|py))\b")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def texts(source: str) -> list[tuple[int, str]]:
    """The (line, text) of every docstring (string statement) and comment of ``source``."""
    found = [
        (node.lineno, node.value.value)
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Expr)
        and isinstance(node.value, ast.Constant)
        and isinstance(node.value.value, str)
    ]
    found += [
        (tok.start[0], tok.string)
        for tok in tokenize.generate_tokens(io.StringIO(source).readline)
        if tok.type == tokenize.COMMENT
    ]
    return found


def references(source: str) -> list[tuple[int, str]]:
    """The (line, reference) of every file named in a docstring or comment of ``source``."""
    refs = []
    for line, text in texts(source):
        for m in REFERENCE.finditer(text):
            if not any(part.split(".")[0] == "NAME" for part in Path(m.group(1)).parts):
                refs.append((line + text[: m.start()].count("\n"), m.group(1)))
    return sorted(set(refs))


def resolves(reference: str, module: Path, repo: Path = REPO) -> bool:
    """Whether ``reference`` names a file relative to the repository root, the package, docs/ or the
    folder of ``module``."""
    package = repo / "src" / "tracegs"
    return any((base / reference).is_file() for base in (repo, package, repo / "docs", module.parent))


def missing_references(files) -> list[str]:
    """``file:line: reference`` for each reference of ``files`` that names no file."""
    out = []
    for path in files:
        for line, ref in references(path.read_text(encoding="utf-8")):
            if not resolves(ref, path):
                out.append(f"{path.relative_to(REPO)}:{line}: {ref}")
    return out


def broken_links(pages) -> list[str]:
    """``page: target`` for each link of ``pages`` that is not a URL or an anchor and names nothing."""
    out = []
    for page in pages:
        for target in LINK.findall(page.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (page.parent / target.split("#")[0]).exists():
                out.append(f"{page.relative_to(REPO)}: {target}")
    return out


def test_references_are_found_and_checked(tmp_path):
    source = (
        '"""See docs/PHYSICS.md and METHOD.md, section 3; the pattern docs/results/NAME.md."""\n'
        "x = 'not_a_docstring.py'  # the rule: ./so3.py\n"
        "def f():\n"
        '    """Cites\n    physics/integrate.py (e.g. RK2)."""\n'
    )
    assert references(source) == [
        (1, "METHOD.md"),
        (1, "docs/PHYSICS.md"),
        (2, "./so3.py"),
        (5, "physics/integrate.py"),
    ]
    module = PACKAGE / "physics" / "free_body.py"
    assert resolves("docs/PHYSICS.md", module) and resolves("physics/integrate.py", module)
    assert resolves("./so3.py", module) and resolves("so3.py", module)
    assert not resolves("METHOD.md", module) and not resolves("so3.py", PACKAGE / "render" / "api.py")
    bad = REPO / "src" / "tracegs" / "physics" / "free_body.py"
    assert missing_references([bad]) == [], "free_body.py's references should resolve"
    page = tmp_path / "page.md"
    page.write_text("[ok](page.md) [web](https://example.org) [anchor](#x) [gone](nowhere.md#y)")
    assert LINK.findall(page.read_text()) == ["page.md", "https://example.org", "#x", "nowhere.md#y"]


def test_every_reference_of_the_package_names_a_file_of_the_repository():
    missing = missing_references(sorted(PACKAGE.rglob("*.py")))
    assert not missing, "references to files that are not in the repository:\n" + "\n".join(missing)


@pytest.mark.parametrize("pages", [["*.md", "benchmarks/*.md"], ["docs/*.md"], ["docs/results/*.md"]])
def test_links_of_the_docs_resolve(pages):
    files = [p for pattern in pages for p in sorted(REPO.glob(pattern))]
    assert files
    broken = broken_links(files)
    assert not broken, "links to nothing:\n" + "\n".join(broken)


LONGEST = {"README.md": 200, "docs/RESULTS.md": 80, "docs/PHYSICS.md": 300, "docs/DESIGN.md": 300}
"""The pages a user reads first, and the most lines each may have (read in five minutes)."""


@pytest.mark.parametrize("page", LONGEST)
def test_the_first_pages_stay_short(page):
    assert len((REPO / page).read_text().splitlines()) <= LONGEST[page]
