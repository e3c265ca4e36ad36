"""Sphinx extension: author-year labels for the book's bibliography.

The in-text citations use ``bibtex_reference_style: author_year`` ("Kalman, 1960"), but
sphinxcontrib-bibtex labels the bibliography list with numbers unless the pybtex style
says otherwise. This registers the pybtex formatting style ``plain_authoryear``: pybtex's
``plain`` style (entries sorted by author, year, title) with labels such as
"Kalman 1960", "Durbin & Koopman 2012" and "Becker et al. 2019", so that the list matches
the citations. Selected in _config.yml with ``bibtex_default_style: plain_authoryear``.
"""

from __future__ import annotations

import codecs
import re
from collections import Counter

import latexcodec  # noqa: F401  (registers the "ulatex" codec)
from pybtex.plugin import register_plugin
from pybtex.style.formatting.plain import Style as PlainStyle
from pybtex.style.labels import BaseLabelStyle


def _plain_text(latex: str) -> str:
    """Turn a BibTeX name fragment such as ``B{\\"u}chler`` into ``Büchler``."""
    text = codecs.decode(latex, "ulatex")
    return re.sub(r"[{}]", "", text).strip()


def _surname(person) -> str:
    parts = person.prelast_names + person.last_names
    return _plain_text(" ".join(parts))


class AuthorYearLabelStyle(BaseLabelStyle):
    """Labels "Surname YEAR", "A & B YEAR" or "A et al. YEAR", made unique with a, b, ..."""

    def format_labels(self, sorted_entries):
        labels = [self._label(entry) for entry in sorted_entries]
        counts = Counter(labels)
        seen: Counter = Counter()
        for label in labels:
            if counts[label] > 1:
                seen[label] += 1
                yield f"{label}{'abcdefghijklmnopqrstuvwxyz'[seen[label] - 1]}"
            else:
                yield label

    @staticmethod
    def _label(entry) -> str:
        persons = entry.persons.get("author") or entry.persons.get("editor") or []
        year = entry.fields.get("year", "n.d.")
        if not persons:
            return f"{_plain_text(entry.fields.get('title', entry.key))[:20]} {year}"
        if len(persons) == 1:
            who = _surname(persons[0])
        elif len(persons) == 2:
            who = f"{_surname(persons[0])} & {_surname(persons[1])}"
        else:
            who = f"{_surname(persons[0])} et al."
        return f"{who} {year}"


class PlainAuthorYearStyle(PlainStyle):
    default_label_style = AuthorYearLabelStyle


def setup(app):
    register_plugin("pybtex.style.formatting", "plain_authoryear", PlainAuthorYearStyle)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}
