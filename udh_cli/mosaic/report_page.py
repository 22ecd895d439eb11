"""``NAME.report.html``: one self-contained page to look at a mosaic run, written beside the mosaic.

It is drawn from the sidecar's dict (the run's results in memory) and each part's preview, with nothing fetched
from a network: the pictures are inline SVG over the preview, embedded as a data URI. Per part it shows the
mosaic with each frame's outline and number, how many frames cover each place, the pair graph (chain, loop
closures, bridges, rejected and failed pairs), the loop closures coloured by their residual after the solve,
and the ground-control or GPS residuals as arrows; then the unplaced frames and why, the stage timings, the
settings and the warnings. It stays readable for long flights: the pictures are vector graphics that scale,
and the only lists of frames (unplaced frames, warnings) are cut at :data:`MAX_ROWS` with a count of the rest.
"""

from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path, PurePath
from typing import Any

import cv2
import numpy as np

from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.outputs.files import RunFiles
from udh_cli.mosaic.outputs.staging import StagedFiles

MAX_ROWS = 40  # rows of a list of frames or warnings shown before "and N more (see the sidecar)"
PANEL_SIDE = 900  # longest side of each picture, CSS pixels; the SVG scales with the window
# Pair graph: (CSS colour, dash pattern) per kind of pair, the order the legend lists them.
PAIR_STYLES = {
    "chain": ("#d0d0d0", ""),
    "loop closure": ("#3b8bd9", ""),
    "bridged": ("#3cb371", ""),
    "rejected": ("#ff9f1a", "6,4"),
    "failed": ("#e0413a", "2,4"),
}


def pair_style(pair: dict[str, Any]) -> str:
    """The pair graph's name for a pair of the sidecar (a key of :data:`PAIR_STYLES`)."""
    if pair["status"] == "failed":
        return "failed"
    if pair["status"] != "ok":
        return "rejected"
    if pair["kind"] in ("bridge", "gps"):
        return "bridged"
    return "loop closure" if (pair.get("consistency_px") or {}).get("loop") else "chain"


def overlap_counts(outlines: list[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """How many frame outlines (each (4, 2) in picture pixels) cover each pixel of a (height, width) picture."""
    counts = np.zeros(size, np.uint16)
    mask = np.zeros(size, np.uint8)
    for outline in outlines:
        mask[:] = 0
        cv2.fillPoly(mask, [np.round(outline).astype(np.int32)], 1)
        counts += mask
    return counts


def residual_colour(value: float, limit: float) -> str:
    """Green (0) through yellow to red (``limit`` and above), as CSS."""
    t = min(1.0, max(0.0, value / limit)) if limit > 0 else 1.0
    red, green = (int(255 * min(1.0, 2 * t)), int(255 * min(1.0, 2 * (1 - t))))
    return f"#{red:02x}{green:02x}30"


def build_report_page(report: dict[str, Any], previews: dict[int, bytes | None]) -> str:
    """The page's HTML for the sidecar dict ``report``; ``previews``: part number -> that part's preview as
    JPEG bytes (None: the frames' outlines are drawn on a dark ground instead)."""
    summary = report["summary"]
    title = f"udh mosaic of {source_label(report['source'])}"
    body = [f"<h1>{_e(title)}</h1>", _summary_table(report), _sequence_section(report)]
    for part in report["parts"]:
        body.append(_part_section(report, part, previews.get(part["part"])))
    body.append(_unplaced_section(report))
    body.append(_timings_section(report["timings_s"]))
    body.append(_settings_section(report))
    warnings = report.get("warnings") or []
    if warnings:
        body.append(f"<details><summary>{len(warnings)} warnings</summary>{_list(warnings)}</details>")
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{_e(title)}</title>"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><style>{_CSS}</style></head>\n"
            f"<body>\n{''.join(body)}\n<p class=\"note\">{summary['frames']} frames; written by udh {_e(report['udh_version'])}; "
            f"every number here is also in the sidecar JSON.</p></body></html>\n")


def write_report_page(report: dict[str, Any], staged: StagedFiles, files: RunFiles) -> Path:
    """Stage ``NAME.report.html`` (``files.report_page``) in ``staged``, each part's preview taken from its staged
    file; returns the final path. ``report`` names the page already (``report_page``), as the sidecar does."""
    folder = files.output.parent
    staged_by_final = {Path(final).resolve(): temporary for temporary, final in staged.staged}
    previews = {}
    for part in report["parts"]:
        temporary = staged_by_final.get((folder / part["preview"]).resolve()) if part.get("preview") else None
        previews[part["part"]] = temporary.read_bytes() if temporary is not None and temporary.is_file() else None
    path = files.report_page
    atomic_write_bytes(staged.path_for(path), build_report_page(report, previews).encode())
    return path


def rewrite_report_page(report: dict[str, Any], folder: Path) -> None:
    """Write the page of a published run again from ``report`` (its sidecar's dict, changed since), the previews
    read from ``folder``, where the sidecar is; nothing when the run wrote no page."""
    if not report.get("report_page"):
        return
    previews = {}
    for part in report["parts"]:
        path = folder / part["preview"] if part.get("preview") else None
        previews[part["part"]] = path.read_bytes() if path is not None and path.is_file() else None
    atomic_write_bytes(folder / report["report_page"], build_report_page(report, previews).encode())


# ------------------------------------------------------------------------------------------ sections


def _summary_table(report: dict[str, Any]) -> str:
    s, loops = report["summary"], report["loop_consistency"]
    by_style: dict[str, int] = {}
    for pair in report["pairs"]:
        by_style[pair_style(pair)] = by_style.get(pair_style(pair), 0) + 1
    rows = [("frames placed", f"{s['placed']} of {s['frames']}" + (f" ({s['skipped_files']} files skipped)" if s["skipped_files"] else "")),
            ("parts", str(s["parts"])),
            ("pairs", ", ".join(f"{by_style.get(k, 0)} {k}" for k in PAIR_STYLES)),
            ("loop closures (px, reference frame)", _loops_text(loops)),
            ("method", report["method"] + (f", fallback {report['fallback']}" if report.get("fallback") else ""))]
    for part in report["parts"]:
        georeference = part.get("georeference")
        if georeference:
            rows.append((f"part {part['part']} on the map", _georeference_text(georeference)))
    if "ground_truth_error" in report and report["ground_truth_error"]["solved"].get("frames"):
        solved = report["ground_truth_error"]["solved"]
        rows.append(("error vs ground truth (px)", f"{solved['mean_corner_px']:.3f} mean, {solved['max_corner_px']:.3f} max corner"))
    if report.get("live"):
        live = report["live"]
        rows.append(("live mode", f"{live['frames']} frames, {live['refreshes']} refresh{'' if live['refreshes'] == 1 else 'es'}, ended by {live['ended_by']}; "
                                  f"the final mosaic is {live.get('final', 'a final run')}"))
    rows.append(("total time", f"{report['timings_s'].get('total', sum(report['timings_s'].values())):.1f} s"))
    return "<table class=\"summary\">" + "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in rows) + "</table>"


PART_COLOURS = ("#4e79a7", "#f28e2b", "#59a14f", "#b07aa1", "#76b7b2", "#edc948", "#ff9da7", "#9c755f", "#e15759", "#bab0ac")


def _sequence_section(report: dict[str, Any]) -> str:
    """The flight in sequence order: each frame a cell coloured by its part (grey: unplaced), and under each
    link to the next frame the fate of that consecutive pair, so that where a flight broke shows at a glance."""
    frames, step = report["frames"], 10
    cells = []
    for record in frames:
        colour = PART_COLOURS[(record["part"] - 1) % len(PART_COLOURS)] if record["part"] else "#111"
        tip = f"{record['index']}: {record['file']}, " + (f"part {record['part']}" if record["part"] else "unplaced")
        cells.append(f'<rect x="{record["index"] * step}" y="0" width="{step - 1}" height="16" fill="{colour}"><title>{_e(tip)}</title></rect>')
    for pair in report["pairs"]:
        if pair["kind"] == "consecutive":
            colour = PAIR_STYLES[pair_style(pair)][0]
            cells.append(f'<rect x="{pair["a"] * step + step / 2}" y="20" width="{step}" height="8" fill="{colour}">'
                         f'<title>{pair["a"]}-{pair["b"]}: {_e(pair["status"])}</title></rect>')
    width = max(1, len(frames)) * step
    svg = (f'<svg class="sequence" viewBox="0 0 {width} 30" preserveAspectRatio="none" xmlns="http://www.w3.org/2000/svg">'
           f'{"".join(cells)}</svg>')
    return _figure(svg, "The frames in sequence order, coloured by part (black: not placed); below, each consecutive pair: "
                        + _pair_legend([p for p in report["pairs"] if p["kind"] == "consecutive"]))


def _loops_text(loops: dict[str, Any]) -> str:
    before, after = loops["loops_before"], loops["loops_after"]
    if not after.get("count"):
        return "none"
    return (f"{after['count']} loops: {after['mean_px']:.2f} mean, {after['max_px']:.2f} max after the solve "
            f"({before['mean_px']:.2f} / {before['max_px']:.2f} chained)")


def _georeference_text(georeference: dict[str, Any]) -> str:
    if georeference["source"] == "gcp":
        used = sum(p["used"] for p in georeference["gcps"].values())
        return (f"{georeference['crs']}, {used} ground-control points, {georeference['gcp_checkpoint_rms_m']:.2f} m RMS at checkpoints, "
                f"{georeference['pixel_size_m'] * 100:.1f} cm per pixel")
    return (f"{georeference['crs']}, {georeference['gps_frames']} frames' GPS, {georeference['gps_residual_rms_m']:.1f} m RMS, "
            f"{georeference['pixel_size_m'] * 100:.1f} cm per pixel")


def _part_section(report: dict[str, Any], part: dict[str, Any], preview: bytes | None) -> str:
    frames = {r["index"]: r for r in report["frames"] if r["part"] == part["part"] and r["mosaic_from_frame"] is not None}
    scale = PANEL_SIDE / max(part["width"], part["height"])
    size = (max(1, round(part["width"] * scale)), max(1, round(part["height"] * scale)))
    to_panel = np.diag([scale, scale, 1.0])
    outlines = {i: _outline(to_panel @ np.array(r["mosaic_from_frame"]), r["width"], r["height"]) for i, r in frames.items()}
    centres = {i: o.mean(axis=0) for i, o in outlines.items()}
    font = max(3.0, 0.09 * float(np.median([np.ptp(o[:, 0]) for o in outlines.values()]))) if outlines else 8.0
    preview_id = f"preview-{part['part']}"  # embedded once, under the mosaic, and reused under the pair graph
    background = _image(preview, size, element_id=preview_id) if preview is not None else f'<rect width="{size[0]}" height="{size[1]}" fill="#282828"/>'

    shapes = "".join(f'<polygon points="{_points(o)}" class="outline"/>' for o in outlines.values())
    numbers = "".join(f'<text x="{c[0]:.1f}" y="{c[1]:.1f}" font-size="{font:.1f}">{i}</text>' for i, c in centres.items())
    mosaic = _svg(size, background + shapes + numbers)

    counts = overlap_counts(list(outlines.values()), (size[1], size[0]))
    overlap = _svg(size, _image(_overlap_png(counts), size, "png") + shapes.replace('class="outline"', 'class="outline faint"'))

    pairs = [p for p in report["pairs"] if p["a"] in centres and p["b"] in centres]
    lines = []
    for name in PAIR_STYLES:  # drawn in legend order: the failures on top
        colour, dash = PAIR_STYLES[name]
        lines += [_line(centres[p["a"]], centres[p["b"]], colour, dash) for p in pairs if pair_style(p) == name]
    graph = _svg(size, (f'<use href="#{preview_id}"/>' if preview is not None else background) + '<rect width="100%" height="100%" fill="#000" opacity="0.45"/>' + "".join(lines)
                 + "".join(f'<circle cx="{c[0]:.1f}" cy="{c[1]:.1f}" r="{font / 4:.1f}" fill="#fff"/>' for c in centres.values()))

    limit = float(report["config"].get("outlier_px") or 5.0)
    loops = [p for p in pairs if pair_style(p) == "loop closure"]
    residuals = _svg(size, shapes.replace('class="outline"', 'class="outline faint"') + "".join(
        _line(centres[p["a"]], centres[p["b"]], residual_colour(p["consistency_px"]["after"], limit), "", width=2.5,
              title=f"{p['a']}-{p['b']}: {p['consistency_px']['after']:.2f} px") for p in loops))

    stats = _overlap_stats(counts)
    parts = [f"<h2>Part {part['part']}: {_e(part['file'])} ({part['width']}x{part['height']} px, {len(part['frames'])} frames, "
             f"drawn on the {_e(part['plane'])})</h2>",
             "<div class=\"grid\">",
             _figure(mosaic, "The mosaic, each frame's outline and number (its index in the sequence)."),
             _figure(overlap, f"Frames covering each place: {stats}. " + _overlap_legend(int(counts.max()) if counts.size else 0)),
             _figure(graph, "The pair graph between frame centres: " + _pair_legend(pairs)),
             _figure(residuals, f"Loop closures after the solve, coloured by residual: green 0 px, yellow {limit / 2:g}, red {limit:g} px "
                                f"(the outlier limit) or more; {len(loops)} loops. Hover a line for its value.")]
    vectors = _residual_vectors(report, part, frames, to_panel, size, shapes)
    if vectors:
        parts.append(vectors)
    parts.append("</div>")
    return "".join(parts)


def _residual_vectors(report, part, frames, to_panel, size, shapes) -> str:
    """Ground-control or GPS residuals as arrows from where the mosaic puts a point to where the map has it."""
    georeference = part.get("georeference")
    if not georeference:
        return ""
    mosaic_from_map = np.linalg.inv(np.array(georeference["map_from_mosaic"]))
    arrows: list[tuple[np.ndarray, np.ndarray, str, float]] = []  # (from, to) in mosaic pixels, label, metres
    if georeference["source"] == "gcp":
        for name, point in georeference["gcps"].items():
            if "mosaic_px" in point:
                target = (mosaic_from_map @ [*point["map_m"], 1.0])[:2]
                arrows.append((np.array(point["mosaic_px"]), target, name + ("" if point["used"] else " (left out)"), point["residual_m"]))
        what = "ground-control point"
    else:
        try:
            from udh_cli.mosaic.georef.gps import utm_transformer

            to_map = utm_transformer(int(georeference["crs"].split(":")[1]))
        except Exception:  # noqa: BLE001 - no pyproj: the page goes without the arrows
            return ""
        for i, record in frames.items():
            meta = record.get("metadata") or {}
            if "latitude" in meta and "longitude" in meta:
                east, north = to_map.transform(meta["longitude"], meta["latitude"])
                centre = (np.array(record["mosaic_from_frame"]) @ [(record["width"] - 1) / 2, (record["height"] - 1) / 2, 1.0])
                centre = centre[:2] / centre[2]
                target = (mosaic_from_map @ [east, north, 1.0])[:2]
                arrows.append((centre, target, str(i), float(np.hypot(*(np.array(georeference["map_from_mosaic"])[:2, :2] @ (target - centre))))))
        what = "frame centre to its GPS fix"
    if not arrows:
        return ""
    lengths = [np.linalg.norm((to_panel[:2, :2] @ (b - a))) for a, b, _, _ in arrows]
    gain = max(1.0, 0.06 * max(size) / max(float(np.median(lengths)), 1e-6))  # the median arrow a few % of the picture
    drawn = []
    for a, b, label, metres in arrows:
        start = (to_panel @ [*a, 1.0])[:2]
        end = start + gain * (to_panel[:2, :2] @ (b - a))
        drawn.append(_line(start, end, "#ff5030", "", width=2, marker=True, title=f"{label}: {metres:.2f} m")
                     + f'<text x="{start[0]:.1f}" y="{start[1]:.1f}" font-size="11" class="label">{_e(label)}</text>')
    picture = _svg(size, shapes.replace('class="outline"', 'class="outline faint"') + "".join(drawn))
    return _figure(picture, f"Residuals, {what} (arrows drawn {gain:.0f}x longer than they are; hover one for metres): "
                            f"median {float(np.median([m for *_, m in arrows])):.2f} m, largest {max(m for *_, m in arrows):.2f} m.")


def _unplaced_section(report: dict[str, Any]) -> str:
    unplaced = [r for r in report["frames"] if r["status"] != "placed"]
    skipped = report.get("skipped_files") or []
    if not unplaced and not skipped:
        return "<h2>Unplaced frames</h2><p>Every frame is in the mosaic.</p>"
    rows = [(r["file"], r["reason"] or "") for r in unplaced] + [(s["file"], "skipped: " + s["reason"]) for s in skipped]
    shown = "".join(f"<tr><td>{_e(name)}</td><td>{_e(_short(reason, 300))}</td></tr>" for name, reason in rows[:MAX_ROWS])
    more = f"<p>and {len(rows) - MAX_ROWS} more (see the sidecar)</p>" if len(rows) > MAX_ROWS else ""
    return (f"<h2>Unplaced frames: {len(unplaced)}, skipped files: {len(skipped)}</h2>"
            f"<table class=\"list\"><tr><th>frame</th><th>why</th></tr>{shown}</table>{more}")


def _timings_section(timings: dict[str, float]) -> str:
    stages = {k: v for k, v in timings.items() if k != "total"}
    longest = max(stages.values(), default=0.0) or 1.0
    rows = "".join(f"<tr><td>{_e(k)}</td><td class=\"num\">{v:.1f} s</td><td><div class=\"bar\" style=\"width:{100 * v / longest:.1f}%\"></div></td></tr>"
                   for k, v in stages.items())
    total = f"<tr><th>total</th><th class=\"num\">{timings['total']:.1f} s</th><td></td></tr>" if "total" in timings else ""
    return f"<h2>Stage timings (wall clock)</h2><table class=\"timings\">{rows}{total}</table>"


def _settings_section(report: dict[str, Any]) -> str:
    config = report["config"]
    rows = "".join(f"<tr><th>{_e(k)}</th><td>{_e(json.dumps(v))}</td></tr>" for k, v in config.items())
    method = {"method": report["method"], "method_settings": report.get("method_settings"), "fallback": report.get("fallback"),
              "fallback_settings": report.get("fallback_settings"), "camera": report.get("camera")}
    return (f"<h2>Settings</h2><table class=\"list\">{rows}</table>"
            f"<details><summary>estimators and camera</summary><pre>{_e(json.dumps(method, indent=1))}</pre></details>")


# ------------------------------------------------------------------------------------------ drawing


def _outline(panel_from_frame: np.ndarray, width: int, height: int) -> np.ndarray:
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [width - 1, height - 1, 1], [0, height - 1, 1]], np.float64)
    mapped = corners @ panel_from_frame.T
    return mapped[:, :2] / mapped[:, 2:3]


def _points(outline: np.ndarray) -> str:
    return " ".join(f"{x:.1f},{y:.1f}" for x, y in outline)


def _line(a, b, colour: str, dash: str, width: float = 1.5, marker: bool = False, title: str | None = None) -> str:
    extra = (f' stroke-dasharray="{dash}"' if dash else "") + (' marker-end="url(#arrow)"' if marker else "")
    inner = f"<title>{_e(title)}</title>" if title else ""
    return (f'<line x1="{a[0]:.1f}" y1="{a[1]:.1f}" x2="{b[0]:.1f}" y2="{b[1]:.1f}" stroke="{colour}" '
            f'stroke-width="{width}"{extra}>{inner}</line>')


def _svg(size: tuple[int, int], content: str) -> str:
    return (f'<svg viewBox="0 0 {size[0]} {size[1]}" xmlns="http://www.w3.org/2000/svg" role="img">'
            '<defs><marker id="arrow" viewBox="0 0 10 10" refX="9" refY="5" markerWidth="6" markerHeight="6" orient="auto">'
            f'<path d="M0,0 L10,5 L0,10 z" fill="#ff5030"/></marker></defs>{content}</svg>')


def _image(data: bytes, size: tuple[int, int], kind: str = "jpeg", element_id: str | None = None) -> str:
    uri = f"data:image/{kind};base64,{base64.b64encode(data).decode('ascii')}"
    named = f' id="{element_id}"' if element_id else ""
    return f'<image{named} href="{uri}" width="{size[0]}" height="{size[1]}" preserveAspectRatio="none"/>'


def _overlap_png(counts: np.ndarray) -> bytes:
    """The overlap count as a PNG: one colour per count (viridis), transparent where no frame is."""
    top = max(1, int(counts.max()))
    scaled = (np.minimum(counts, top).astype(np.float32) * (255.0 / top)).astype(np.uint8)
    colour = cv2.applyColorMap(scaled, cv2.COLORMAP_VIRIDIS)
    rgba = np.dstack([colour, np.where(counts > 0, 255, 0).astype(np.uint8)])
    ok, encoded = cv2.imencode(".png", rgba)
    return encoded.tobytes() if ok else b""


def _overlap_legend(top: int) -> str:
    if top < 1:
        return ""
    swatches = []
    for count in sorted({1, *range(1, top + 1, max(1, math.ceil(top / 8))), top}):
        b, g, r = cv2.applyColorMap(np.array([[round(count * 255 / top)]], np.uint8), cv2.COLORMAP_VIRIDIS)[0, 0]
        swatches.append(f'<span class="swatch" style="background:#{r:02x}{g:02x}{b:02x}"></span>{count}')
    return "Colours: " + " ".join(swatches)


def _overlap_stats(counts: np.ndarray) -> str:
    covered = counts[counts > 0]
    if covered.size == 0:
        return "no frame"
    return (f"median {int(np.median(covered))}, at most {int(covered.max())}; {100 * np.mean(covered >= 2):.0f} % of the mapped area "
            f"is seen by 2 or more frames, {100 * np.mean(covered >= 3):.0f} % by 3 or more")


def source_label(source: str) -> str:
    """The source as a title names it: its last two folders, without the ``..`` steps of a path relative to the
    output folder (the sidecar's ``source``): ``copr/images``, not ``../../data/flights/copr/images``."""
    named = [part for part in PurePath(source).parts if part not in ("..", ".", "/")]
    return "/".join(named[-2:]) or source


def _pair_legend(pairs: list[dict[str, Any]]) -> str:
    """The styles of ``pairs``, each with its count; a style no pair has is left out."""
    counts = {name: sum(pair_style(p) == name for p in pairs) for name in PAIR_STYLES}
    return " ".join(f'<span class="swatch line" style="border-top:3px {"dashed" if dash else "solid"} {colour}"></span>{name} {counts[name]}'
                    for name, (colour, dash) in PAIR_STYLES.items() if counts[name])


def _figure(svg: str, caption: str) -> str:
    return f"<figure>{svg}<figcaption>{caption}</figcaption></figure>"


def _list(items: list[str]) -> str:
    shown = "".join(f"<li>{_e(_short(item, 400))}</li>" for item in items[:MAX_ROWS])
    more = f"<li>and {len(items) - MAX_ROWS} more (see the sidecar)</li>" if len(items) > MAX_ROWS else ""
    return f"<ul>{shown}{more}</ul>"


def _short(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _e(value: Any) -> str:
    return html.escape(str(value))


_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em auto;max-width:1900px;padding:0 1em;color:#222;background:#fafafa}
h1{font-size:1.5em} h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0} th,td{text-align:left;padding:2px 10px;vertical-align:top}
table.summary th{color:#555;font-weight:normal} table.list td,table.list th{border-bottom:1px solid #e4e4e4}
.num{text-align:right;font-variant-numeric:tabular-nums} .timings td:last-child{width:40em}
.bar{height:10px;background:#3b8bd9}
.grid{display:grid;grid-template-columns:repeat(auto-fit,minmax(420px,1fr));gap:1.2em}
figure{margin:0;background:#fff;border:1px solid #ddd;padding:6px} svg{width:100%;height:auto;display:block;background:#1e1e1e}
figcaption{font-size:.9em;color:#444;margin-top:4px} svg.sequence{height:48px;background:#fff}
.outline{fill:none;stroke:#ffd24a;stroke-width:1} .outline.faint{stroke:#ffffff;stroke-opacity:.35}
text{fill:#fff;paint-order:stroke;stroke:#000;stroke-width:2px;text-anchor:middle;dominant-baseline:middle;font-family:sans-serif}
text.label{text-anchor:start;font-size:11px}
.swatch{display:inline-block;width:14px;height:10px;margin:0 3px 0 8px} .swatch.line{height:0;width:20px;vertical-align:middle}
pre{font-size:12px;background:#f0f0f0;padding:8px;overflow:auto} .note{color:#777;font-size:.85em}
"""
