"""The API reference's griffe extension (docs/hooks/sphinx_roles.py) turns Sphinx roles into autorefs links.

griffe comes with the ``test`` extra (and with ``docs``).
"""

import importlib.util
import textwrap

import pytest

from tests.docs.shown_outputs import ROOT

griffe = pytest.importorskip("griffe")

spec = importlib.util.spec_from_file_location("sphinx_roles", ROOT / "docs" / "hooks" / "sphinx_roles.py")
sphinx_roles = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sphinx_roles)

SOURCE = textwrap.dedent('''
    """Module.

    .. code-block:: python

        x = 1
    """


    def load():
        """Load."""


    class Thing:
        """See :func:`load`, :meth:`Thing.run`, :class:`~pkg.mod.Other`, :mod:`numpy.linalg` and :func:`nowhere`."""

        def run(self):
            """Run; then :attr:`size`."""

        size = 1


    class Other:
        """Other."""
''')


def test_roles_become_optional_autorefs_resolved_in_scope(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "mod.py").write_text(SOURCE)
    pkg = griffe.load("pkg", search_paths=[str(tmp_path)], extensions=griffe.load_extensions(sphinx_roles.SphinxRoles))
    mod = pkg["mod"]
    thing = mod["Thing"].docstring.value
    assert '<autoref identifier="pkg.mod.load" optional><code>load</code></autoref>' in thing
    assert '<autoref identifier="pkg.mod.Thing.run" optional><code>Thing.run</code></autoref>' in thing
    assert '<autoref identifier="pkg.mod.Other" optional><code>Other</code></autoref>' in thing  # ~ keeps the last part
    # outside the package, or unknown: plain code, never a dangling link
    assert "<code>numpy.linalg</code>" in thing and "<code>nowhere</code>" in thing
    assert 'identifier="numpy' not in thing and ":func:" not in thing and ":mod:" not in thing
    # a method's roles resolve in its class
    assert '<autoref identifier="pkg.mod.Thing.size" optional><code>size</code></autoref>' in mod["Thing"]["run"].docstring.value
    # the directive line goes, its indented block stays (a Markdown code block)
    assert ".. code-block::" not in mod.docstring.value and "    x = 1" in mod.docstring.value
