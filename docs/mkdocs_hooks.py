"""MkDocs hooks of the documentation site (``mkdocs.yml``: ``hooks``).

- The home page is the README, the contributing and changelog pages CONTRIBUTING.md and
  CHANGELOG.md, read at build time
  (their links into ``docs/`` rewritten), so the site and the repository never drift apart.
- The API reference has one page per public module of ``src/mpcmobo``, generated here from the
  package tree (``griffe``, the loader mkdocstrings uses), so a new module gets its page and its
  nav entry without editing ``mkdocs.yml``. A package's page lists its public names
  (``__all__``) with links to where they are defined.
- Nav entries marked optional (``optional_pages`` in ``extra``) are dropped while their file does
  not exist, so ``mkdocs build --strict`` passes before those pages are written.
"""

from __future__ import annotations

import re
from pathlib import Path

import griffe
from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
SRC = ROOT / "src"
PACKAGE = "mpcmobo"
ROOT_PAGES = {
    "index.md": "README.md",
    "contributing.md": "CONTRIBUTING.md",
    "changelog.md": "CHANGELOG.md",
}


def _public_modules() -> list[griffe.Module]:
    """Every module of the package whose dotted path has no private part, in tree order."""
    found: list[griffe.Module] = []

    def walk(module: griffe.Module) -> None:
        found.append(module)
        for sub in _submodules(module):
            walk(sub)

    walk(griffe.load(PACKAGE, search_paths=[str(SRC)], resolve_aliases=True))
    return found


def _submodules(module: griffe.Module) -> list[griffe.Module]:
    """The public modules of a package (not the modules its code imports)."""
    subs = module.modules.items()
    return [m for n, m in sorted(subs) if not n.startswith("_") and not m.is_alias]


def _first_line(obj: griffe.Object) -> str:
    return obj.docstring.value.strip().splitlines()[0] if obj.docstring else ""


def _is_package(module: griffe.Module) -> bool:
    return module.filepath is not None and Path(str(module.filepath)).name == "__init__.py"


def _page(module: griffe.Module) -> str:
    lines = [f"# `{module.path}`", "", f"::: {module.path}"]
    if not _is_package(module):
        return "\n".join(lines) + "\n"
    # a package renders what its __init__ defines itself; its re-exports render in their modules
    # names exported lazily (a module __getattr__) have no member to render here
    exports = [n for n in module.exports or () if n in module.all_members]
    own = [n for n in exports if not module[n].is_alias]
    members = f"[{', '.join(own)}]" if own else "false"
    lines += ["    options:", f"      members: {members}", ""]
    if exports:
        lines += ["## Public names", "", "| name | defined in |", "|---|---|"]
        for name in exports:
            obj = module[name]
            target = obj.target_path if obj.is_alias else obj.path
            home = target.rsplit(".", 1)[0]
            lines.append(f"| [`{name}`][{target}] | [`{home}`]({home}.md) |")
        lines.append("")
    subs = _submodules(module)
    if subs:
        lines += ["## Modules", ""]
        lines += [f"- [`{m.path}`]({m.path}.md): {_first_line(m)}" for m in subs]
    return "\n".join(lines) + "\n"


def _drop_missing_optional(nav: list, optional: set[str], docs_dir: Path) -> list:
    kept = []
    for item in nav:
        if isinstance(item, dict):
            (title, value), = item.items()
            if isinstance(value, list):
                item = {title: _drop_missing_optional(value, optional, docs_dir)}
            elif value in optional and not (docs_dir / value).exists():
                continue
        kept.append(item)
    return kept


def on_config(config: MkDocsConfig) -> MkDocsConfig:
    """Drop missing optional pages from the nav and append the generated API reference."""
    optional = set(config.extra.get("optional_pages", []))
    nav = _drop_missing_optional(config.nav or [], optional, Path(config.docs_dir))
    api = [{m.path: f"api/{m.path}.md"} for m in _public_modules()]
    config.nav = [*nav, {"API reference": api}]
    return config


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the pages read from the repository root and one API page per public module."""
    for page, source in ROOT_PAGES.items():
        text = (ROOT / source).read_text(encoding="utf-8")
        text = re.sub(r"\]\(docs/", "](", text)  # links into docs/ from the repository root
        text = text.replace("](CONTRIBUTING.md)", "](contributing.md)")
        text = text.replace("](CHANGELOG.md)", "](changelog.md)")
        files.append(File.generated(config, page, content=text))
    for module in _public_modules():
        files.append(File.generated(config, f"api/{module.path}.md", content=_page(module)))
    return files
