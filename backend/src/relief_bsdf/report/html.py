"""The house style of the HTML reports (fit and diagnosis): one self-contained file.

Images are embedded as data URIs (the page can be e-mailed), numbers are formatted for a reader
(significant figures, units in the headers), parameters carry their 68 % intervals, and every page
states its units and conventions.  Nothing here computes physics.
"""
from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path
from typing import Any, Iterable

STYLE = """
body{font-family:-apple-system,'Segoe UI',Helvetica,Arial,sans-serif;max-width:1150px;margin:24px auto;
     padding:0 16px;color:#1d1d1f;line-height:1.45}
h1{font-size:1.6em;margin-bottom:0.2em} h2{font-size:1.2em;border-bottom:1px solid #ddd;padding-bottom:3px;
     margin-top:1.6em} .sub{color:#555;margin-top:0}
table{border-collapse:collapse;margin:8px 0 12px 0} th,td{border:1px solid #d0d0d0;padding:3px 9px;font-size:13px}
th{background:#f3f3f6;text-align:left} td.num{text-align:right;font-variant-numeric:tabular-nums}
.verdict{padding:8px 12px;border-radius:5px;margin:10px 0} .ok{background:#e7f6ea;border:1px solid #9fd3aa}
.warn{background:#fff6e0;border:1px solid #f0c96b} .bad{background:#fdeaea;border:1px solid #e7a3a3}
figure{margin:12px 0} figure img{max-width:100%;border:1px solid #e3e3e3}
figcaption{font-size:13px;color:#444;margin-top:4px} .small{font-size:12px;color:#555}
dl.kv{display:grid;grid-template-columns:max-content auto;gap:2px 14px;font-size:13px} dl.kv dt{font-weight:600}
dl.kv dd{margin:0}
"""

CONVENTIONS = (
    "Angles in degrees. Directions point away from the sample; theta from the sample normal (+z, the lit side) "
    "for reflection R and from -z for transmission T; phi is the azimuth, phi_i of the source. Signed scatter "
    "angle: negative on the phi_s = phi_i + 180 half-plane (the specular / undeviated side), positive on "
    "phi_s = phi_i. BSDF values are Nicodemus BSDFs in 1/sr, not cosine-corrected "
    "(f = P_detector / (P_incident * Omega * cos theta_s)); transmission values are radiance BTDFs. "
    "Wavelengths are vacuum wavelengths in nm. Intervals are 68 % (one sigma) intervals.")


def esc(x: Any) -> str:
    return html.escape(str(x))


def fmt(x: Any, digits: int = 4) -> str:
    """A number for a reader: `digits` significant figures, no float noise; text passes through."""
    if x is None:
        return "n/a"
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        try:
            x = float(x)
        except (TypeError, ValueError):
            return esc(x)
    if isinstance(x, int):
        return str(x)
    if not math.isfinite(x):
        return "n/a" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if x == 0:
        return "0"
    if 1e-3 <= abs(x) < 1e5:
        return f"{x:.{digits}g}"
    return f"{x:.{max(digits - 1, 1)}e}"


def data_uri(source: str | Path | bytes) -> str:
    """PNG file (or its bytes) as a data: URI."""
    raw = source if isinstance(source, bytes) else Path(source).read_bytes()
    return "data:image/png;base64," + base64.b64encode(raw).decode("ascii")


def figure_png(fig, dpi: int = 100) -> bytes:
    """The PNG bytes of a matplotlib figure (closed afterwards)."""
    import matplotlib.pyplot as plt
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def figure_html(source: str | Path | bytes, caption: str) -> str:
    return (f'<figure><img src="{data_uri(source)}" alt="{esc(caption)}"><figcaption>{esc(caption)}'
            "</figcaption></figure>")


def table_html(header: Iterable[str], rows: Iterable[Iterable[Any]], numeric: bool = True) -> str:
    """An HTML table; cells that are numbers are formatted with `fmt` and right-aligned."""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = []
    for r in rows:
        cells = []
        for c in r:
            if numeric and isinstance(c, (int, float)) and not isinstance(c, bool):
                cells.append(f'<td class="num">{fmt(c)}</td>')
            else:
                cells.append(f"<td>{c if isinstance(c, Raw) else esc(c)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


class Raw(str):
    """Already-escaped HTML for a table cell."""


PARAMETER_UNITS = {"height_scale": ("height scale", "x measured heights"),
                   "filter_sigma_um": ("Gaussian filter sigma", "um")}


def parameter_rows(parameters: dict, intervals: dict | None) -> list[list]:
    """Rows (name, unit, value, 68 % interval) for a parameter table.

    `intervals` {name: [lo, hi] | None}: None (or a missing name) is shown as "not determined";
    no `intervals` at all: "not computed"."""
    rows = []
    for name, value in parameters.items():
        label, unit = PARAMETER_UNITS.get(name, (name.replace("_", " "), _unit_from_name(name)))
        if intervals is None:
            iv = "not computed"
        else:
            lohi = intervals.get(name)
            iv = "not determined" if lohi is None or len(lohi) != 2 or lohi[0] is None or lohi[1] is None \
                else f"[{fmt(lohi[0])}, {fmt(lohi[1])}]"
        rows.append([label, unit, value if isinstance(value, (int, float)) else str(value), iv])
    return rows


def _unit_from_name(name: str) -> str:
    for suffix, unit in (("_per_mm", "1/mm"), ("_per_m", "1/m"), ("_um", "um"), ("_nm", "nm"), ("_deg", "deg"),
                         ("_per_sr", "1/sr"), ("_m", "m")):
        if name.endswith(suffix):
            return unit
    return ""


def correlation_html(correlation: Any) -> str:
    """A correlation matrix given as {a: {b: r}} or {"names": [...], "matrix": [[...]]}; '' if absent."""
    if not correlation:
        return ""
    if isinstance(correlation, dict) and "names" in correlation and "matrix" in correlation:
        names, m = list(correlation["names"]), correlation["matrix"]
    elif isinstance(correlation, dict) and all(isinstance(v, dict) for v in correlation.values()):
        names = list(correlation)
        m = [[correlation[a].get(b, 1.0 if a == b else None) for b in names] for a in names]
    else:
        return f"<p class='small'>correlation: {esc(correlation)}</p>"
    rows = [[n] + [(float(v) if v is not None else "n/a") for v in row] for n, row in zip(names, m)]
    return "<p>Correlation of the fitted parameters:</p>" + table_html([""] + names, rows)


def kv_html(d: dict, depth: int = 0) -> str:
    """A nested dict as a definition list with formatted numbers."""
    items = []
    for k, v in d.items():
        if isinstance(v, dict):
            val = kv_html(v, depth + 1) if v else "none"
        elif isinstance(v, (list, tuple)):
            val = ", ".join(fmt(x) if isinstance(x, (int, float)) else esc(x) for x in v) or "none"
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            val = fmt(v)
        else:
            val = esc(v)
        items.append(f"<dt>{esc(str(k).replace('_', ' '))}</dt><dd>{val}</dd>")
    return f"<dl class='kv'>{''.join(items)}</dl>"


def page(title: str, subtitle: str, sections: Iterable[str]) -> str:
    """The whole self-contained page."""
    return (f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>'
            f"<style>{STYLE}</style></head><body><h1>{esc(title)}</h1><p class='sub'>{subtitle}</p>"
            + "\n".join(sections) + "</body></html>")


def section(heading: str, body: str) -> str:
    return f"<h2>{esc(heading)}</h2>\n{body}"


def user_paths(obj: Any, sample_path: str | Path, out_dir: str | Path | None = None) -> Any:
    """`obj` (a JSON-like document) with every absolute path of this machine that a job derived from the
    user's own paths written back in the user's terms: the sample file's folder as the user named it
    (a relief "relief.npz" beside "runs/sample.toml" is "runs/relief.npz", not the resolved absolute
    path), likewise the output folder.  A path the user gave absolute stays absolute."""
    import os
    import re
    pairs = []
    for given in (Path(sample_path).parent, None if out_dir is None else Path(out_dir)):
        if given is None:
            continue
        resolved = os.path.abspath(given)
        shown = str(given) if str(given) not in ("", ".") else "."
        if resolved != shown and len(Path(resolved).parts) > 1:        # never the file-system root
            # the folder itself, or followed by a separator; not a longer name that starts with it
            pat = re.compile(re.escape(resolved) + r"(?:(" + re.escape(os.sep) + r")|(?![\w.\-]))")
            pairs.append((len(resolved), pat, shown))
    pairs.sort(key=lambda p: -p[0])

    def one(x: str) -> str:
        for _, pat, shown in pairs:
            x = pat.sub(lambda m, shown=shown: (("" if shown == "." else shown + m.group(1)) if m.group(1)
                                                else shown), x)
        return x

    def fix(x: Any) -> Any:
        if isinstance(x, str):
            return one(x)
        if isinstance(x, dict):
            return {k: fix(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [fix(v) for v in x]
        return x
    return fix(obj)
