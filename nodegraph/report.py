"""The run report: OUT/report.html, a page that opens from disk, with its pictures beside it in OUT/report/.

It reads OUT/run.json (see run.py) and shows, in graph order:
    - the graph picture (nodes coloured by status, edges labelled with ports),
    - per node: a table of its work items (frame, status, cache hit, wall time, error, log and published files),
      previews of its outputs (nodegraph.preview) for at most MAX_PREVIEW_FRAMES evenly sampled frames,
      its Table outputs as HTML and their numeric metrics plotted over all frames.
Everything is read from the cache folders named in run.json, so `report OUT` works after the run.
"""
from __future__ import annotations

import html
import json
import os
import shutil
from pathlib import Path

import networkx as nx
import numpy as np

from .errors import DataError, VolcapError
from .graphfile import topological_order
from .preview import MAX_WIDTH, numeric_series, preview
from .records import frames_of

MAX_PREVIEW_FRAMES = 8
STATUS_COLOURS = {"done": "#7ac27a", "cached": "#8fb8e0", "failed": "#e07070", "skipped": "#c8c8c8"}
# a companion found among a node's ancestors decorates its previews (masks over images, 3-D views by cameras)
ANCESTOR_COMPANIONS = ("Images", "Cameras")


def write_report(out_dir: Path) -> Path:
    """Write out_dir/report.html (pictures in out_dir/report/) from out_dir/run.json; return its path."""
    out_dir = Path(out_dir).resolve()
    run_file = out_dir / "run.json"
    if not run_file.is_file():
        raise DataError(f"{run_file}: no run record; run a graph with `--out {out_dir}` first")
    try:
        run = json.loads(run_file.read_text())
        items = run["items"]
    except (ValueError, KeyError) as exc:
        raise DataError(f"{run_file}: not a run record ({exc})") from None
    pics = out_dir / "report"
    shutil.rmtree(pics, ignore_errors=True)
    pics.mkdir(parents=True)

    by_node: dict[str, list[dict]] = {}
    for rec in items:
        by_node.setdefault(rec["node"], []).append(rec)
    for recs in by_node.values():
        recs.sort(key=lambda r: -1 if r["frame"] is None else r["frame"])
    dag = graph_of(run, by_node)
    order = topological_order({n: list(dag.predecessors(n)) for n in dag}, {n: i for i, n in enumerate(by_node)}) \
        or list(by_node)
    status = {n: node_status(by_node[n]) for n in by_node}
    draw_graph(dag, status, pics / "graph.png")

    sections = [_node_section(name, by_node[name], by_node, dag, out_dir, pics) for name in order]
    page = _page(run, out_dir, order, status, by_node, sections)
    target = out_dir / "report.html"
    target.write_text(page, encoding="utf-8")
    return target


# ---------------------------------------------------------------- graph
def graph_of(run: dict, by_node: dict) -> nx.DiGraph:
    """The run's graph: nodes (attribute ``type``) and edges (attribute ``label`` 'out→in'), from the graph
    file via load_graph; from the raw YAML when its node types cannot be loaded here; else nodes only."""
    dag = nx.DiGraph()
    for name, recs in by_node.items():
        dag.add_node(name, type=recs[0].get("type", "?"))
    edges = []
    try:
        from .graphfile import load_graph

        g = load_graph(run["graph"], run.get("overrides") or [])
        edges = [(src, name, _port_label(sport, port)) for name, spec in g.nodes.items() for port, (src, sport) in spec.inputs.items()]
    except (VolcapError, OSError, KeyError):
        edges = _raw_edges(run.get("graph"))
    for src, dst, label in edges:
        if src in dag and dst in dag:
            old = dag.edges[src, dst]["label"] + "\n" if dag.has_edge(src, dst) else ""
            dag.add_edge(src, dst, label=old + label)
    return dag


def _raw_edges(path) -> list[tuple[str, str, str]]:
    import yaml

    try:
        doc = yaml.safe_load(Path(path).read_text())
        edges = []
        for name, entry in (doc.get("nodes") or {}).items():
            for port, ref in ((entry or {}).get("in") or {}).items():
                src, _, sport = str(ref).partition(".")
                edges.append((name, port, src, sport))
        return [(src, name, _port_label(sport, port)) for name, port, src, sport in edges]
    except (OSError, TypeError, AttributeError, yaml.YAMLError):
        return []


def _port_label(out_port: str, in_port: str) -> str:
    return out_port if out_port == in_port else f"{out_port}→{in_port}"


def node_status(recs: list[dict]) -> str:
    """One word for a node: failed / skipped if any item is, cached if all are, else done."""
    states = {r["status"] for r in recs}
    for s in ("failed", "skipped"):
        if s in states:
            return s
    return "cached" if states == {"cached"} else "done"


def draw_graph(dag: nx.DiGraph, status: dict, out_png: Path) -> Path:
    """Nodes in columns by topological generation, coloured by status; edges labelled with their ports."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    gens = list(nx.topological_generations(dag)) if nx.is_directed_acyclic_graph(dag) else [list(dag)]
    for layer, names in enumerate(gens):
        for n in names:
            dag.nodes[n]["layer"] = layer
    pos = nx.multipartite_layout(dag, subset_key="layer") if len(dag) > 1 else {n: np.zeros(2) for n in dag}
    tallest = max((len(g) for g in gens), default=1)
    width = min(1200, 120 + 170 * len(gens))
    height = min(800, 100 + 75 * tallest)
    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.axis("off")
    xs = np.array([p[0] for p in pos.values()]) if pos else np.zeros(1)
    ys = np.array([p[1] for p in pos.values()]) if pos else np.zeros(1)
    pad_x, pad_y = 0.12 * (np.ptp(xs) or 1) + 0.15, 0.2 * (np.ptp(ys) or 1) + 0.12
    ax.set_xlim(xs.min() - pad_x, xs.max() + pad_x)
    ax.set_ylim(ys.min() - pad_y, ys.max() + pad_y)
    boxes = {n: ax.text(x, y, f"{n}\n({dag.nodes[n].get('type', '?')})", ha="center", va="center", fontsize=7, zorder=3,
                        bbox={"boxstyle": "round,pad=0.4", "fc": STATUS_COLOURS.get(status.get(n), "#eeeeee"), "ec": "#444444"})
             for n, (x, y) in pos.items()}
    canvas.draw()  # box extents are known after a draw
    to_px, to_data = ax.transData, ax.transData.inverted()
    for u, v, data in dag.edges(data=True):
        span = dag.nodes[v]["layer"] - dag.nodes[u]["layer"]
        rad = 0.0 if span <= 1 else min(0.12 * span, 0.35)  # long edges bend around the columns between
        ax.annotate("", xy=pos[v], xytext=pos[u], zorder=2, annotation_clip=False,
                    arrowprops={"arrowstyle": "-|>", "color": "#777777", "lw": 0.9, "shrinkA": 2, "shrinkB": 2,
                                "patchA": boxes[u].get_bbox_patch(), "patchB": boxes[v].get_bbox_patch(),
                                "connectionstyle": f"arc3,rad={rad}"})
        a, b = to_px.transform(pos[u]), to_px.transform(pos[v])
        d = b - a
        mid = (a + b) / 2 + 0.5 * rad * np.array([d[1], -d[0]])  # the arc's midpoint (matplotlib arc3 control point / 2)
        ax.text(*to_data.transform(mid), data.get("label", ""), fontsize=6, ha="center", va="center", zorder=4,
                bbox={"fc": "white", "ec": "none", "alpha": 0.85, "pad": 0.5})
    for artist in ax.get_children():  # long arcs may leave the axes: keep them and grow the picture instead
        artist.set_clip_on(False)
    fig.savefig(str(out_png), bbox_inches="tight", pad_inches=0.15, facecolor="white")
    return out_png


# ---------------------------------------------------------------- per node
def output_types(type_name: str, cache_dir: Path) -> dict[str, str]:
    """Output port -> type name: from the node's declaration, or from the cache entry's record when the node
    type cannot be imported here (e.g. a plugin that is not installed)."""
    try:
        from .node import node_class

        cls = node_class(type_name)
        return {port: out.type.name for port, out in cls.outputs.items()}
    except (VolcapError, ImportError):
        try:
            return dict(json.loads((cache_dir / "meta.json").read_text()).get("types", {}))
        except (OSError, ValueError, AttributeError):
            return {}


def sample_frames(recs: list[dict], limit: int = MAX_PREVIEW_FRAMES) -> list[dict]:
    """At most ``limit`` records with outputs, evenly spread over the sequence (first and last included)."""
    have = [r for r in recs if r.get("cache_dir") and Path(r["cache_dir"]).is_dir()]
    if len(have) <= limit:
        return have
    return [have[i] for i in sorted(set(np.linspace(0, len(have) - 1, limit).round().astype(int)))]


def _companions(rec: dict, ports: dict, by_node: dict, dag: nx.DiGraph) -> dict[str, Path]:
    """Type name -> folder: the item's own outputs first, then Images/Cameras of the nearest ancestor node
    of the same frame."""
    own = {t: Path(rec["cache_dir"]) / p for p, t in ports.items() if (Path(rec["cache_dir"]) / p).is_dir()}
    found = {}
    node = rec["node"]
    ancestors = sorted(nx.ancestors(dag, node), key=lambda a: nx.shortest_path_length(dag, a, node)) if node in dag else []
    for anc in ancestors:  # nearest first
        for r in by_node.get(anc, []):
            if r["frame"] not in (rec["frame"], None) or not r.get("cache_dir"):
                continue
            for p, t in output_types(r["type"], Path(r["cache_dir"])).items():
                if t in ANCESTOR_COMPANIONS and t not in found and (Path(r["cache_dir"]) / p).is_dir():
                    found[t] = Path(r["cache_dir"]) / p
    return {**found, **own}


def _node_section(name, recs, by_node, dag, out_dir: Path, pics: Path) -> str:
    st = node_status(recs)
    total = sum(r.get("seconds") or 0.0 for r in recs)
    head = (f'<section class="node" id="node-{_e(name)}" data-node="{_e(name)}">'
            f'<h2><span class="badge {st}">{st}</span> {_e(name)} <small>({_e(recs[0].get("type", "?"))}) — '
            f'{len(recs)} item{"s" if len(recs) != 1 else ""}, {total:.2f} s</small></h2>')
    parts = [head, _items_table(recs, out_dir)]
    picked = sample_frames(recs)
    if len(picked) < len([r for r in recs if r.get("cache_dir")]):
        parts.append(f'<p class="note">previews of {len(picked)} evenly sampled frames</p>')
    tables: dict[str, list[tuple]] = {}
    for rec in [r for r in recs if r.get("cache_dir") and Path(r["cache_dir"]).is_dir()]:
        ports = output_types(rec["type"], Path(rec["cache_dir"]))
        for port, t in ports.items():
            if t == "Table" and (Path(rec["cache_dir"]) / port).is_dir():
                tables.setdefault(port, []).append((rec["frame"], Path(rec["cache_dir"]) / port))
    for rec in picked:
        figures = _previews(name, rec, by_node, dag, out_dir)
        if figures:
            frame = "all frames" if rec["frame"] is None else f"frame{'s' * ('frames' in rec)} {frames_of(rec)}"
            parts.append(f'<div class="frame"><h4>{frame}</h4><div class="previews">' + "".join(figures) + "</div></div>")
    for port, series in tables.items():
        parts.append(_metrics_block(name, port, series, out_dir, pics))
    parts.append("</section>")
    return "\n".join(parts)


def _previews(name: str, rec: dict, by_node: dict, dag: nx.DiGraph, out_dir: Path) -> list[str]:
    """<figure> elements with a preview of each output of one work item."""
    cache_dir = Path(rec["cache_dir"])
    ports = output_types(rec["type"], cache_dir)
    comps = _companions(rec, ports, by_node, dag)
    own = {t for p, t in ports.items() if (cache_dir / p).is_dir()}
    frame = frames_of(rec)
    figures = []
    for port, t in ports.items():
        folder = cache_dir / port
        if port in (rec.get("in_memory") or []):
            figures.append(f'<figure class="in-memory"><figcaption>{_e(port)} <small>{_e(t)}</small></figcaption>'
                           '<p class="note">kept in memory only (run with --report or --keep-all to keep it)</p></figure>')
            continue
        if not folder.is_dir() or (t == "Bounds" and "Cameras" in own):  # the cameras picture shows the box
            continue
        rel = Path("report") / _slug(name) / f"{frame}_{_slug(port)}.png"
        caption = f"{_e(port)} <small>{_e(t)}</small>"
        try:
            made = preview(t, folder, out_dir / rel, companions=comps)
        except Exception as exc:  # one bad preview must not sink the report
            figures.append(f'<figure class="preview-error"><figcaption>{caption}</figcaption>'
                           f'<pre>preview failed: {_e(type(exc).__name__)}: {_e(exc)}</pre></figure>')
            continue
        if made is not None:
            figures.append(f'<figure><img src="{_e(rel.as_posix())}" alt="{_e(name)}.{_e(port)} frame {frame}">'
                           f'<figcaption>{caption}</figcaption></figure>')
    return figures


def _items_table(recs: list[dict], out_dir: Path) -> str:
    rows = []
    for r in recs:
        frame = frames_of(r)
        log = r.get("log")
        log_link = f'<a href="{_e(_rel(log, out_dir))}">log</a>' if log and Path(log).is_file() else ""
        files = " ".join(f'<a href="{_e(_rel(f, out_dir))}">{_e(Path(f).name)}</a>' for f in r.get("published") or [])
        err = f'<pre class="error">{_e(r["error"])}</pre>' if r.get("error") else ""
        rows.append(f'<tr class="{_e(r["status"])}"><td>{frame}</td><td>{_e(r["status"])}</td>'
                    f'<td>{"yes" if r.get("cache_hit") else "no"}</td><td>{(r.get("seconds") or 0.0):.3f}</td>'
                    f'<td>{err}</td><td>{log_link}</td><td>{files}</td></tr>')
    table = ('<table class="items"><thead><tr><th>frame</th><th>status</th><th>cache hit</th><th>seconds</th>'
             '<th>error</th><th>log</th><th>published</th></tr></thead><tbody>' + "".join(rows) + "</tbody></table>")
    if len(recs) > 12:
        return f"<details><summary>{len(recs)} work items</summary>{table}</details>"
    return table


def _metrics_block(name: str, port: str, series: list[tuple], out_dir: Path, pics: Path) -> str:
    """HTML tables of a Table output (sampled frames) and a plot of its numeric scalars over all frames."""
    loaded = []
    for frame, folder in series:
        try:
            loaded.append((frame, json.loads((folder / "table.json").read_text())))
        except (OSError, ValueError):
            continue
    parts = [f'<h3>{_e(port)} <small>metrics</small></h3>']
    picked = [loaded[i] for i in sorted(set(np.linspace(0, len(loaded) - 1, min(len(loaded), MAX_PREVIEW_FRAMES)).round().astype(int)))] if loaded else []
    keys: list[str] = []
    flat = []
    for frame, table in picked:
        f = _flatten(table)
        flat.append((frame, f))
        keys += [k for k in f if k not in keys]
    if picked:
        head = "".join(f"<th>frame {'all' if fr is None else fr}</th>" for fr, _ in flat)
        body = "".join(f"<tr><th>{_e(k)}</th>" + "".join(f"<td>{_e(_fmt(f.get(k, '')))}</td>" for _, f in flat) + "</tr>"
                       for k in keys[:60])
        parts.append(f'<table class="metrics" data-port="{_e(port)}"><thead><tr><th></th>{head}</tr></thead><tbody>{body}</tbody></table>')
    over = [(fr, numeric_series(t)[0]) for fr, t in loaded if fr is not None]
    if len(over) > 1:
        rel = Path("report") / _slug(name) / f"metrics_{_slug(port)}.png"
        plot_metrics(over, out_dir / rel)
        parts.append(f'<figure class="metrics-plot"><img src="{_e(rel.as_posix())}" alt="{_e(name)}.{_e(port)} over frames">'
                     f'<figcaption>{_e(port)} over frames</figcaption></figure>')
    return "\n".join(parts)


def plot_metrics(over: list[tuple[int, dict]], out_png: Path, max_panels: int = 9) -> Path:
    """Small multiples: each numeric scalar of a table against the frame number."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    keys = []
    for _, s in over:
        keys += [k for k in s if k not in keys]
    keys = keys[:max_panels]
    cols = min(3, max(len(keys), 1))
    rows = max(1, -(-len(keys) // cols))
    fig = Figure(figsize=(MAX_WIDTH / 100, 1.6 * rows + 0.3), dpi=100)
    FigureCanvasAgg(fig)  # attaches the Agg canvas savefig draws with
    for i, k in enumerate(keys):
        ax = fig.add_subplot(rows, cols, i + 1)
        pts = [(fr, s[k]) for fr, s in over if k in s]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="." if len(pts) < 60 else None, color="#4a7fc0")
        ax.set_title(k, fontsize=7)
        ax.tick_params(labelsize=6)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    for artist in ax.get_children():  # long arcs may leave the axes: keep them and grow the picture instead
        artist.set_clip_on(False)
    fig.savefig(str(out_png), bbox_inches="tight", pad_inches=0.15, facecolor="white")
    return out_png


# ---------------------------------------------------------------- page
CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;color:#222}
h1{font-size:1.5em;margin:0} h2{font-size:1.15em;border-bottom:1px solid #ddd;padding-bottom:.2em}
h2 small,h3 small,figcaption small{color:#777;font-weight:normal}
table{border-collapse:collapse;margin:.4em 0;font-size:12px} td,th{border:1px solid #ddd;padding:2px 6px;text-align:left;vertical-align:top}
tr.failed td{background:#fbe3e3} tr.skipped td{background:#f0f0f0}
.badge{display:inline-block;border-radius:3px;padding:0 6px;font-size:12px} .done{background:#7ac27a}
.cached{background:#8fb8e0} .failed{background:#e07070} .skipped{background:#c8c8c8}
pre.error,.preview-error pre{white-space:pre-wrap;margin:0;color:#900;max-width:60em}
.previews{display:flex;flex-wrap:wrap;gap:10px} figure{margin:0} figure img{max-width:300px;border:1px solid #ccc;display:block}
figcaption{font-size:12px} h4{margin:.6em 0 .2em;font-size:13px;color:#555} .note{color:#777;font-size:12px} nav a{margin-right:.8em}
"""


def _page(run, out_dir, order, status, by_node, sections) -> str:
    counts = ", ".join(f"{v} {k}" for k, v in sorted((run.get("counts") or {}).items()))
    frames = run.get("frames") or []
    frame_text = f"{frames[0]}…{frames[-1]} ({len(frames)})" if frames else "?"
    nav = " ".join(f'<a href="#node-{_e(n)}"><span class="badge {status[n]}">{_e(n)}</span></a>' for n in order)
    failed = [r for r in run.get("items", []) if r["status"] == "failed"]
    fail_html = ""
    if failed:
        fail_html = "<h2>Failures</h2><ul>" + "".join(
            f'<li><a href="#node-{_e(r["node"])}">{_e(r["node"])}</a> frame {frames_of(r)}: '
            f'{_e(r.get("error", ""))}</li>' for r in failed) + "</ul>"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>volcap run — {_e(Path(run.get("graph", "?")).name)}</title>
<style>{CSS}</style></head><body>
<h1>volcap run report: {_e(Path(run.get("graph", "?")).name)}</h1>
<p>graph <code>{_e(run.get("graph", "?"))}</code> · frames {_e(frame_text)} · {run.get("seconds", 0):.2f} s · {_e(counts)}<br>
output <code>{_e(out_dir)}</code> · cache <code>{_e(run.get("cache", "?"))}</code></p>
<nav>{nav}</nav>
<figure id="graph"><img src="report/graph.png" alt="graph" style="max-width:100%"></figure>
{fail_html}
{"".join(sections)}
</body></html>
"""


def _flatten(table: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in table.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):  # records: one row per field
            for field_name in v[0]:
                out[f"{prefix}{k}.{field_name}"] = [x.get(field_name) for x in v]
        else:
            out[f"{prefix}{k}"] = v
    return out


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        text = ", ".join(_fmt(x) for x in v[:24])
        return f"[{text}{', …' if len(v) > 24 else ''}]"
    return str(v)


def _rel(path: str, base: Path) -> str:
    return Path(os.path.relpath(path, base)).as_posix()


def _slug(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(s))


def _e(s) -> str:
    return html.escape(str(s), quote=True)
