"""The Library page holds to the page's rules (tests/api/test_hardening_web.py): nothing inline that
the Content-Security-Policy would have to allow, and no string ever parsed as HTML (file names, labels and
reasons are user text)."""

from __future__ import annotations

import re

from app.api.app import WEB_DIR
from tests.api.test_hardening_web import _Inline


def test_library_html_has_nothing_inline():
    parser = _Inline()
    parser.feed((WEB_DIR / "library.html").read_text())
    assert parser.found == []


def test_library_js_never_parses_strings_as_html():
    js = (WEB_DIR / "library.js").read_text()
    for sink in ("innerHTML", "outerHTML", "insertAdjacentHTML", "document.write", "bindPopup(`", "html:"):
        assert sink not in js, sink


def test_library_js_binds_tooltips_and_popups_to_elements_only():
    """Leaflet parses a string given to bindTooltip/bindPopup as HTML (a template, a variable holding
    text, a concatenation alike): the page gives them an element made by ``el`` only."""
    js = (WEB_DIR / "library.js").read_text()
    calls = re.findall(r"\.(bind(?:Tooltip|Popup)|setTooltipContent|setPopupContent)\(\s*([^)]{0,20})", js)
    assert calls, "the page binds tooltips (the check must see them)"
    for name, arg in calls:
        assert arg.startswith("el("), (name, arg)
