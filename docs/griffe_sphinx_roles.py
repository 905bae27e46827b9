"""A griffe extension for the API reference (mkdocs.yml): the docstrings cross-reference in
Sphinx's roles (``:func:`calibrate```, ``:class:`~mavcal.run.Options```), which Markdown would
show as they are typed; each becomes a code span of the name (``~`` keeps its last part)."""
from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|attr|data|exc|obj|const):`(~?)([^`]+)`")


def _code(m: re.Match) -> str:
    name = m.group(2)
    return f"`{name.rsplit('.', 1)[-1] if m.group(1) else name}`"


class SphinxRoles(griffe.Extension):
    def on_instance(self, *, obj: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_code, obj.docstring.value)
