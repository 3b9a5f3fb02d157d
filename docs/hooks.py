"""MkDocs hook for `make docs`: the docstrings' maths is plain text, not Markdown.

The module docstrings of `gpguided_jax` write vectors and block matrices in brackets, e.g.
``[e; -1][e; -1]^T``, which Markdown reads as a reference link and mkdocs-autorefs then reports as
an unknown cross-reference. Such a warning is shown as information instead, so that
`mkdocs build --strict` still fails on every other warning, a cross-reference to a Python object
(a dotted name) that does not exist included. `KNOWN_DOCSTRING_ISSUES` lists the docstring
problems of the code that are reported but do not fail the build; remove an entry once its
docstring is fixed.
"""

import logging
import re

# (logger, substring of the message) pairs shown as information, not warnings.
KNOWN_DOCSTRING_ISSUES: tuple[tuple[str, str], ...] = ()
_NOT_A_PYTHON_NAME = re.compile(r"Could not find cross-reference target '(?![\w.]+')")


class _Downgrade(logging.Filter):
    def __init__(self, patterns):
        super().__init__()
        self.patterns = patterns

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno == logging.WARNING:
            message = record.getMessage()
            if any(p(message) for p in self.patterns):
                record.levelno, record.levelname = logging.INFO, "INFO"
        return True


def on_startup(command, dirty):  # noqa: ARG001 (mkdocs' hook signature)
    logging.getLogger("mkdocs.plugins.mkdocs_autorefs._internal.plugin").addFilter(
        _Downgrade([lambda m: bool(_NOT_A_PYTHON_NAME.search(m))]))
    for name in {logger for logger, _ in KNOWN_DOCSTRING_ISSUES}:
        texts = [text for logger, text in KNOWN_DOCSTRING_ISSUES if logger == name]
        logging.getLogger(f"mkdocs.plugins.{name}").addFilter(
            _Downgrade([lambda m, t=t: t in m for t in texts]))
