"""Griffe extension for the API reference: the docstrings' reST markup as mkdocstrings renders it.

bayescal's numpydoc docstrings cross-reference with Sphinx roles
(``:func:`load```, ``:class:`~bayescal.bayes.linear.LinearisedModel```) and
show code with ``.. code-block::``; mkdocstrings renders docstrings as
Markdown, where a role would print as ``:func:`` before the name.  Each role
becomes an *optional* autorefs link to its target, resolved in the scope of
the object the docstring belongs to (as Sphinx resolves it): a link where the
target is on a page of the reference, plain code where it is not (an optional
reference never fails the strict build).  A ``.. code-block::`` line is
dropped: the indented block under it is a Markdown code block as it stands.
Loaded by mkdocs.yml (``extensions`` of the python handler).
"""

from __future__ import annotations

import html
import re

import griffe

ROLE = re.compile(r":(?:func|class|meth|attr|data|mod|exc|obj):`(?P<tilde>~?)(?P<target>[\w.]+)(?:\(\))?`")
CODE_BLOCK = re.compile(r"^[ \t]*\.\. code-block::.*\n", flags=re.MULTILINE)


def _identifier(obj: griffe.Object, target: str) -> str | None:
    """The full path of ``target`` seen from ``obj`` (None if it cannot be resolved)."""
    if target.startswith(f"{obj.package.name}."):
        return target
    head, _, rest = target.partition(".")
    scope = obj if obj.is_class or obj.is_module else obj.parent
    try:
        path = scope.resolve(head) if scope is not None else None
    except griffe.NameResolutionError:
        return None
    return f"{path}.{rest}" if path and rest else path


def convert(obj: griffe.Object, text: str) -> str:
    """``text`` with its roles as optional autorefs and its ``.. code-block::`` lines dropped."""

    def link(match: re.Match) -> str:
        target = match["target"]
        title = f"<code>{html.escape(target.rsplit('.', 1)[-1] if match['tilde'] else target)}</code>"
        identifier = _identifier(obj, target)
        if identifier is None:
            return title
        return f'<autoref identifier="{html.escape(identifier)}" optional>{title}</autoref>'

    return ROLE.sub(link, CODE_BLOCK.sub("", text))


class SphinxRoles(griffe.Extension):
    """Rewrite every docstring of a package once it is loaded (names resolve against the whole package)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        self._walk(pkg)

    def _walk(self, obj: griffe.Object) -> None:
        if obj.docstring is not None:
            obj.docstring.value = convert(obj, obj.docstring.value)
        for member in obj.members.values():
            if not member.is_alias:
                self._walk(member)
