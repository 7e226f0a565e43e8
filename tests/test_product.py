"""What the 1.0 release promises of the repository as a product, read from its files.

* No numbered references to past work (a work session, an issue or a pull request named by its
  number) in the code, the tests, the benchmarks or the documentation: each text says what is,
  in the present tense.
* Each learner has few user options (at most 8 for ``bo`` and ``mpc-rl``, 12 for ``mobo`` and
  ``hybrid``), and every one, nested tables included, is documented: ``mpcmobo run --help`` and
  the configuration reference are generated from those descriptions.
* The README's test command is what CI runs, and docs/configuration.md is the generated
  reference itself.

The size of the code is held by ruff's complexity rules (``C901``, ``PLR0911``-``PLR0915``, their
thresholds in pyproject.toml), not here; documents are as long as their content needs.

Each check lists what breaks it, so that a failure says where to look.
"""

from __future__ import annotations

import re
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from mpcmobo.experiment.options_doc import _models, configuration_reference
from mpcmobo.learners.registry import LEARNER_SPECS, option_fields

ROOT = Path(__file__).parents[1]
NUMBERED = re.compile(r"[Ss]ession [0-9]|[Ii]ssue [0-9]|#[0-9]{2}")
SEARCHED = ["src", "tests", "benchmarks", "docs", "README.md", "CONTRIBUTING.md"]
SKIPPED_SUFFIXES = {".png", ".pdf"}


# ---------------------------------------------------------------------- numbered references
def _text_files(root: Path, names: list[str]) -> list[Path]:
    """The files under ``names`` (files or directories of ``root``), without caches, build
    metadata and images."""
    out = []
    for name in names:
        path = root / name
        candidates = [path] if path.is_file() else sorted(path.rglob("*"))
        for p in candidates:
            parts = p.relative_to(root).parts
            if not p.is_file() or p.suffix.lower() in SKIPPED_SUFFIXES:
                continue
            if "__pycache__" in parts or any(part.endswith(".egg-info") for part in parts):
                continue
            out.append(p)
    return out


def _read_text(path: Path) -> str | None:
    """The file's text, or None for a binary file (a NUL byte, or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def numbered_references(root: Path, names: list[str]) -> list[str]:
    """``path:line: text`` of every line under ``names`` that matches :data:`NUMBERED`."""
    hits = []
    for path in _text_files(root, names):
        text = _read_text(path)
        if text is None:
            continue
        for i, line in enumerate(text.splitlines(), 1):
            if NUMBERED.search(line):
                hits.append(f"{path.relative_to(root)}:{i}: {line.strip()[:100]}")
    return hits


def _ref(text: str) -> str:
    """``text`` with its ``~`` removed: the samples below would otherwise be numbered
    references in this very file."""
    return text.replace("~", "")


def test_the_reference_check_finds_what_it_must_and_skips_binaries(tmp_path):
    """The checker itself: each form of a numbered reference is found in a text file, and
    images, binary files, caches and build metadata are not read."""
    (tmp_path / "src" / "__pycache__").mkdir(parents=True)
    (tmp_path / "src" / "x.egg-info").mkdir()
    (tmp_path / "src" / "a.py").write_text(
        _ref("ok = 1\n# Sess~ion 4 found it\nsee iss~ue 7\nfixed in #~12\nrefs #1 and issue-10\n")
    )
    (tmp_path / "src" / "b.md").write_text(_ref("as the sess~ion 12 notes say\n"))
    (tmp_path / "src" / "__pycache__" / "a.py").write_text(_ref("sess~ion 1\n"))
    (tmp_path / "src" / "x.egg-info" / "PKG-INFO").write_text(_ref("iss~ue 1\n"))
    (tmp_path / "src" / "fig.png").write_bytes(_ref("\x89PNG sess~ion 1").encode("latin-1"))
    (tmp_path / "src" / "data.bin").write_bytes(_ref("\0iss~ue 3").encode())
    (tmp_path / "README.md").write_text(_ref("Iss~ue 9\n"))
    hits = numbered_references(tmp_path, ["src", "README.md", "missing.md"])
    assert hits == [
        _ref("src/a.py:2: # Sess~ion 4 found it"),
        _ref("src/a.py:3: see iss~ue 7"),
        _ref("src/a.py:4: fixed in #~12"),
        _ref("src/b.md:1: as the sess~ion 12 notes say"),
        _ref("README.md:1: Iss~ue 9"),
    ]


def test_no_numbered_references_to_past_work():
    hits = numbered_references(ROOT, SEARCHED)
    assert not hits, f"{len(hits)} lines name a session or issue by number:\n" + "\n".join(
        hits[:200]
    )


# ---------------------------------------------------------------------- learner options
MAX_OPTIONS = {"mpc-rl": 8, "bo": 8, "mobo": 12, "hybrid": 12, "identify": 8}


def test_each_learner_has_few_user_options():
    assert set(MAX_OPTIONS) == set(LEARNER_SPECS), "a learner without a limit of options"
    counts = {name: len(option_fields(name)) for name in LEARNER_SPECS}
    over = {n: c for n, c in counts.items() if c > MAX_OPTIONS[n]}
    assert not over, f"options per learner {counts}, limits {MAX_OPTIONS}"
    assert all(c > 0 for c in counts.values()), counts  # the registry reads the options


def undocumented(model: type[BaseModel], prefix: str) -> list[str]:
    """The fields of ``model`` and of its nested tables (a table, or each variant of a policy
    table) without a description. A variant's ``rule`` is its name: the variant's class
    docstring describes it (the reference prints it), so that docstring must not be empty."""
    out = []
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        if name == "rule":
            if not (model.__doc__ or "").strip():
                out.append(f"{key} (the class {model.__name__} has no docstring)")
        elif not (field.description or "").strip():
            out.append(key)
        for sub in _models(field.annotation):
            out += undocumented(sub, f"{key}.")
    return out


def test_every_learner_option_is_documented():
    missing = []
    for name, spec in LEARNER_SPECS.items():
        assert spec.options is not None, name
        missing += undocumented(spec.options, f"learner_options.{name}.")
    assert not missing, "options without a description (docstring):\n" + "\n".join(missing)


def test_the_documentation_check_looks_into_nested_tables():
    class Inner(BaseModel):
        """A table."""

        model_config = ConfigDict(use_attribute_docstrings=True)
        depth: int = 1
        """Documented."""
        width: int = 2

    class Variant(BaseModel):
        rule: str = "v"

    class Outer(BaseModel):
        model_config = ConfigDict(use_attribute_docstrings=True)
        table: Inner = Inner()
        """A documented table."""
        policy: Variant | Inner = Variant()
        count: int = 3

    assert undocumented(Outer, "x.") == [
        "x.table.width",
        "x.policy",
        "x.policy.rule (the class Variant has no docstring)",
        "x.policy.width",
        "x.count",
    ]


# ---------------------------------------------------------------------- documents
def test_ci_runs_the_readme_test_command():
    """The README's two set-up commands are its only ``bash`` blocks that start with ``python3 -m
    venv``; the one that runs pytest is what ``.ci/run`` runs, verbatim."""
    blocks = re.findall(r"```bash\n(python3 -m venv [^\n]*)\n```", (ROOT / "README.md").read_text())
    assert len(blocks) == 2, blocks
    (test_command,) = [b for b in blocks if "pytest" in b]
    assert test_command in (ROOT / ".ci" / "run").read_text().splitlines()


def test_the_configuration_page_is_the_generated_reference():
    """docs/configuration.md is ``configuration_reference()`` byte for byte: a changed option
    or docstring changes the page, which is then generated again by the maintainers."""
    page = ROOT / "docs" / "configuration.md"
    assert page.exists(), f"{page} does not exist"
    assert page.read_text(encoding="utf-8") == configuration_reference()
