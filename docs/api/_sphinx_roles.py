"""Griffe extension for the API reference: render the docstrings' Sphinx roles as Markdown.

The package's docstrings are Google style with Sphinx cross-reference roles (``:func:`greedy```,
``:class:`~torchmisspec.data.Trajectories```, ``:mod:`torchmisspec.gp._mll```) and the odd reST literal-block
marker (``Typical use::``). Markdown shows those roles verbatim. Before mkdocstrings parses the docstrings, this
extension rewrites each role:

* into an autorefs link ``[`name`][public.path]`` when the target is rendered in the API reference, i.e. it has a
  docstring and a public path in one of the ``modules`` given as options (members of rendered classes included);
* into plain code ``` `name` ``` otherwise (private modules, other packages, names that do not resolve), so a role
  never produces a broken link or a strict-mode warning.

``~`` (show the last component) and leading-dot names (relative to the enclosing modules) follow Sphinx. The docs
build loads this file through the mkdocstrings option ``extensions`` (see ``mkdocs.yml``); ``exclude_docs`` keeps it
out of the built site. It changes only the docstrings griffe loaded for the docs, never the package.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|attr|mod|data|exc|obj|const):`(~?)([^`<>]+?)`")
LITERAL_MARKER = re.compile(r"(\S)::(?=\n)")  # "Typical use::" -> "Typical use:" (the block stays a code block)


def _target(obj: griffe.Object | griffe.Alias) -> griffe.Object | None:
    try:
        return obj.final_target if isinstance(obj, griffe.Alias) else obj
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


class SphinxRoles(griffe.Extension):
    """Rewrite Sphinx roles in the docstrings of a package (see the module docstring)."""

    def __init__(self, modules: list[str] | None = None, exclude: list[str] | None = None) -> None:
        super().__init__()
        self.modules = list(modules or [])  # documented modules, most specific first
        self.exclude = set(exclude or [])  # public paths not rendered (e.g. deprecated names)

    # ------------------------------------------------------------------------------------------------ public paths
    def _public_paths(self, pkg: griffe.Module) -> dict[str, str]:
        """Canonical path -> the public path under which the API reference renders it (first module wins)."""
        paths: dict[str, str] = {}

        def add(public: str, obj: Any) -> None:
            target = _target(obj)
            if target is None or public in self.exclude or not target.docstring:
                return
            paths.setdefault(target.path, public)
            if target.is_class:
                for name, member in target.members.items():
                    if not name.startswith("_") and not isinstance(member, griffe.Alias):
                        add(f"{public}.{name}", member)

        for module_path in self.modules:
            try:
                module = pkg.modules_collection[module_path]
            except (KeyError, ValueError):
                continue
            if module.docstring:
                paths.setdefault(module.path, module_path)
            exports = None if module.exports is None else {str(name) for name in module.exports}
            for name, member in module.members.items():
                if name.startswith("_") or (exports is not None and name not in exports):
                    continue
                target = _target(member)
                if target is not None and not target.is_module:
                    add(f"{module_path}.{name}", target)
        return paths

    # ---------------------------------------------------------------------------------------------- resolution
    @staticmethod
    def _lookup(pkg: griffe.Module, path: str) -> griffe.Object | None:
        try:
            return _target(pkg.modules_collection[path])
        except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            return None

    def _resolve(self, pkg: griffe.Module, owner: griffe.Object, name: str) -> griffe.Object | None:
        scopes = [owner, *self._parents(owner)]
        if name.startswith("."):
            for scope in scopes:
                if scope.is_module and (found := self._lookup(pkg, scope.path + name)) is not None:
                    return found
            return None
        if (found := self._lookup(pkg, name)) is not None:
            return found
        first, _, rest = name.partition(".")
        for scope in scopes:
            try:
                base = scope.resolve(first)
            except griffe.NameResolutionError:
                continue
            found = self._lookup(pkg, f"{base}.{rest}" if rest else base)
            if found is not None:
                return found
        return None

    @staticmethod
    def _parents(obj: griffe.Object) -> list[griffe.Object]:
        out, parent = [], obj.parent
        while parent is not None:
            out.append(parent)
            parent = parent.parent
        return out

    # ------------------------------------------------------------------------------------------------- rewrite
    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        public = self._public_paths(pkg)

        def rewrite(owner: griffe.Object) -> None:
            docstring = owner.docstring
            if docstring is not None and docstring.value:

                def replace(match: re.Match) -> str:
                    tilde, name = match.groups()
                    name = name.strip()
                    shown = name.rsplit(".", 1)[-1] if tilde else name.lstrip(".")
                    target = self._resolve(pkg, owner, name)
                    path = public.get(target.path) if target is not None else None
                    return f"[`{shown}`][{path}]" if path else f"`{shown}`"

                value = ROLE.sub(replace, docstring.value)
                docstring.value = LITERAL_MARKER.sub(r"\1:", value)
            for member in owner.members.values():
                if not isinstance(member, griffe.Alias):
                    rewrite(member)

        rewrite(pkg)
