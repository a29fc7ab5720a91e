"""HTML building blocks of ``report.html``: number formatting, escaped text, tables that fit a phone.

Numbers never print as ``11008502658314538.0``: ``num`` gives significant digits, and scientific
notation (``1.10×10<sup>16</sup>``) for huge and tiny magnitudes. Cells are escaped text unless
they are ``Html`` (markup built here).
"""

from __future__ import annotations

import html
import math

#: Magnitudes printed in scientific notation: at or above ``SCI_HIGH``, or non-zero below ``SCI_LOW``.
SCI_HIGH = 1e6
SCI_LOW = 1e-4

_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


class Html(str):
    """A string that is already HTML (not escaped again by ``cell``/``table``)."""


def esc(text) -> str:
    return html.escape(str(text))


def num(v, sig: int = 4, *, sign: bool = False) -> str:
    """``v`` with ``sig`` significant digits; scientific (×10ⁿ) for |v| ≥ ``SCI_HIGH`` or
    0 < |v| < ``SCI_LOW``; "—" for None/NaN, "∞" for infinities. ``sign``: always show + or −."""
    if v is None:
        return "—"
    v = float(v)
    if math.isnan(v):
        return "—"
    if math.isinf(v):
        return "∞" if v > 0 else "−∞"
    if v == 0:
        return "0"
    a = abs(v)
    if a >= SCI_HIGH or a < SCI_LOW:
        mant, exp = f"{v:.{max(sig - 1, 0)}e}".split("e")
        text = f"{mant}×10{str(int(exp)).translate(_SUPERSCRIPT)}"
    elif a >= 10 ** sig:
        text = f"{v:.0f}"
    else:
        text = f"{v:#.{sig}g}".rstrip(".")  # '#': keep trailing zeros, so a column reads evenly
        if "e" in text:  # e.g. 0.0001234 with sig 4 → keep it positional
            text = f"{v:.{sig - 1 - math.floor(math.log10(a))}f}"
    if sign and v > 0:
        text = "+" + text
    return text.replace("-", "−")


def fixed(v, decimals: int = 4, *, sign: bool = False) -> str:
    """``v`` with a fixed number of decimals (degrees, mm), falling back to ``num`` for magnitudes
    where fixed decimals would print an absurd number of digits or only zeros."""
    if v is None or not math.isfinite(float(v)):
        return num(v)
    v = float(v)
    if v != 0 and (abs(v) >= SCI_HIGH or abs(v) < 0.5 * 10 ** -decimals):
        return num(v, 2, sign=sign)
    text = f"{v:+.{decimals}f}" if sign else f"{v:.{decimals}f}"
    return text.replace("-", "−")


def cell(v) -> str:
    """A table cell's content: ``Html`` as is, numbers through ``num``, text escaped."""
    if isinstance(v, Html):
        return v
    if isinstance(v, bool) or v is None:
        return "—" if v is None else esc(v)
    if isinstance(v, int):
        return f"{v:,}".replace(",", "\u202f")  # counts: all digits, narrow no-break space thousands
    if isinstance(v, float):
        return num(v)
    return esc(v)


def table(header: list[str], rows: list[list], *, left: int = 1, cls: str = "", notes: list[str | None] | None = None,
          groups: list[str | None] | None = None) -> Html:
    """A table in a horizontally scrolling box. ``left``: how many leading columns are text
    (left-aligned). ``notes``: per row, a text shown as a full-width line under the row;
    ``groups``: per row, a full-width heading line above it (None: none)."""
    th = "".join(f'<th{" class=l" if i < left else ""}>{esc(h)}</th>' for i, h in enumerate(header))
    body = []
    for k, r in enumerate(rows):
        group = groups[k] if groups else None
        if group:
            body.append(f'<tr class=group><td class=l colspan="{len(header)}"><div>{cell(group)}</div></td></tr>')
        tds = "".join(f'<td{" class=l" if i < left else ""}>{cell(c)}</td>' for i, c in enumerate(r))
        body.append(f"<tr>{tds}</tr>")
        note = notes[k] if notes else None
        if note:
            body.append(f'<tr class=note><td class=l colspan="{len(header)}"><div>{cell(note)}</div></td></tr>')
    c = f' class="{cls}"' if cls else ""
    return Html(f'<div class=scroll><table{c}><thead><tr>{th}</tr></thead><tbody>{"".join(body)}</tbody></table></div>')


CSS = """
*{box-sizing:border-box}
body{font-family:system-ui,sans-serif;margin:0 auto;padding:1em 2em;max-width:1100px;color:#222;line-height:1.4}
h1{font-size:1.6em;margin:0.3em 0}h2{margin-top:1.6em;border-bottom:1px solid #ddd}
.scroll{overflow-x:auto;max-width:100%;margin:0.5em 0 1.2em}
table{border-collapse:collapse}th,td{border:1px solid #bbb;padding:3px 8px;text-align:right;vertical-align:top}
th{background:#eee}td.l,th.l{text-align:left}tr.note td{font-size:0.85em;color:#555;border-top:none;background:#fafafa}
tr.note div,tr.group div{position:sticky;left:0.5em;max-width:calc(100vw - 3em)}
tr.group td{background:#f3f3f3;font-weight:600}
.warn{color:#a40}.bad{color:#b00}.good{color:#060}.small{font-size:0.85em;color:#555}
svg.fig{max-width:100%;height:auto;border:1px solid #ddd;margin:0.5em 0;background:#fff}
.figs{display:flex;flex-wrap:wrap;gap:0 0.5em}
pre{background:#f6f6f6;padding:0.6em;overflow-x:auto}
pre.wrap,code.wrap{white-space:pre-wrap;overflow-wrap:anywhere}
.summary{border:2px solid #888;border-radius:6px;padding:0.6em 1em;margin:1em 0;background:#fcfcfc}
.summary.ok{border-color:#4a4}.summary.stop{border-color:#c33;background:#fff6f6}
.summary h2{margin-top:0.2em;border:none}.banner{font-size:1.15em;font-weight:600;margin:0.2em 0 0.5em}
.cols{display:flex;flex-wrap:wrap;gap:0 2em}.cols>div{flex:1 1 320px;min-width:0}.cols>div:first-child{flex:1.5 1 380px}
.nw{white-space:nowrap}
ul{padding-left:1.3em}li{margin:0.2em 0}
figure{margin:0.5em 0}figcaption{font-size:0.85em;color:#555}
@media (max-width:600px){body{padding:0.5em 0.7em}h1{font-size:1.3em}th,td{padding:2px 4px}table{font-size:0.9em}
.summary{padding:0.4em 0.5em}}
"""
