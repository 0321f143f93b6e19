"""Graph files: YAML -> a validated Graph. Every problem is reported as 'file:line: message', all at once.

    frames: 0:10                      # half-open range A:B, a single frame N, or a list of frames
    defaults:                         # optional: parameter defaults by node type
      hull: {resolution: 128}
    nodes:
      capture: {type: capture, params: {path: "${VOLCAP_DATA}/thu_wd_human"}}
      hull:    {type: hull, in: {masks: capture.masks, cameras: capture.cameras}}

Path parameters (InPath) expand ${VAR} / ${VAR:-default} and are resolved against the graph file's folder
(so "${VOLCAP_DATA:-../data}/set" reads $VOLCAP_DATA when it is set, else the folder ../data beside the graph).
"""
from __future__ import annotations

import difflib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .errors import GraphError
from .node import REQUIRED, InPath, Node, registry
from .types import compatible, describe_type

MAX_FRAMES = 1_000_000  # a range beyond this is a typo, not a capture
TOP_KEYS = ("frames", "defaults", "nodes", "description")
NODE_KEYS = ("type", "in", "params", "keep", "doc")
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class _Map(dict):
    """A mapping that remembers the line of each key (1-based) and its own line."""

    line: int = 0
    lines: dict


class _Loader(yaml.SafeLoader):
    duplicate_keys: list


# YAML 1.1 reads 1:20 as the base-60 integer 80: frame ranges must stay strings, so drop sexagesimal ints.
_Loader.yaml_implicit_resolvers = {k: [r for r in v if r[0] != "tag:yaml.org,2002:int"]
                                   for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:int",
    re.compile(r"^(?:[-+]?0b[0-1_]+|[-+]?0[0-7_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$"),
    list("-+0123456789"))


def _construct_mapping(loader: _Loader, node, deep=False):
    loader.flatten_mapping(node)
    m = _Map()
    m.line = node.start_mark.line + 1
    m.lines = {}
    for k_node, v_node in node.value:
        k = loader.construct_object(k_node, deep=True)
        if not isinstance(k, (str, int, float, bool, type(None))):  # lists and mappings cannot be keys
            raise yaml.constructor.ConstructorError(None, None, f"a key must be a plain value, not {type(k).__name__}",
                                                    k_node.start_mark)
        if k in m:
            loader.duplicate_keys.append((k_node.start_mark.line + 1, k))
        m[k] = loader.construct_object(v_node, deep=True)
        m.lines[k] = k_node.start_mark.line + 1
    return m


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def parse_yaml(text: str, where: str):
    loader = _Loader(text)
    loader.duplicate_keys = []
    try:
        data = loader.get_single_data()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f"{mark.line + 1}:{mark.column + 1}" if mark else "?"
        raise GraphError([f"{where}:{line}: YAML syntax error: {exc.problem or exc}"]) from None
    except yaml.YAMLError as exc:
        raise GraphError([f"{where}: YAML error: {exc}"]) from None
    finally:
        loader.dispose()
    problems = [f"{where}:{line}: duplicate key '{k}'" for line, k in loader.duplicate_keys]
    return data, problems


def suggest(word: str, options) -> str:
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def expand_path(value: str, base: Path) -> Path:
    """``value`` with ${VAR} / ${VAR:-default} expanded, resolved against ``base``. ValueError names a
    variable that is used without a default and not set."""
    def sub(m):
        name, default = m.group(1), m.group(3)
        if os.environ.get(name):
            return os.environ[name]
        if default is None:
            raise ValueError(f"uses ${{{name}}}, which is not set (set it, or write ${{{name}:-DEFAULT}})")
        return default

    text = re.sub(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(:-([^}]*))?\}", sub, value)
    p = Path(os.path.expanduser(text))
    return (p if p.is_absolute() else base / p).resolve()


@dataclass
class NodeSpec:
    name: str
    type_name: str
    cls: type[Node]
    params: dict                       # coerced values; InPath params are absolute path strings
    inputs: dict                       # port -> (source node, source port)
    line: int
    lines: dict = field(default_factory=dict)   # "param:NAME" / "in:PORT" -> line
    keep: tuple = ()                   # output ports the graph asks to store in the cache (checkpoints)


@dataclass
class Graph:
    path: Path
    frames: list[int]
    nodes: dict[str, NodeSpec]
    upstream: dict[str, list[str]]    # node -> the nodes its inputs come from (file order)
    description: str = ""
    overrides: list = field(default_factory=list)   # the --set arguments it was loaded with

    def keep_all(self) -> "Graph":
        """Store every output of every node in the cache (a report draws them; debugging)."""
        for spec in self.nodes.values():
            spec.keep = tuple(spec.cls.outputs)
        return self

    def order(self) -> list[str]:
        """Node names in dependency order (stable: file order among independent nodes)."""
        pos = {n: i for i, n in enumerate(self.nodes)}
        order = topological_order(self.upstream, pos)
        assert order is not None, "validated graphs have no cycle"
        return order


def parse_frames(value, where: str) -> list[int]:
    if isinstance(value, bool):
        raise ValueError(f"{where}: frames must be A:B, N or a list of frame numbers; got {value!r}")
    if isinstance(value, int):
        return [value]
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return sorted(set(value))
    if isinstance(value, str) and re.fullmatch(r"\s*-?\d+\s*", value):
        return [int(value)]
    if isinstance(value, str):
        m = re.fullmatch(r"\s*(-?\d+)\s*:\s*(-?\d+)\s*", value)
        if m:
            a, b = int(m.group(1)), int(m.group(2))
            if b - a > MAX_FRAMES:
                raise ValueError(f"{where}: frame range {value!r} has {b - a} frames (at most {MAX_FRAMES})")
            if b > a:
                return list(range(a, b))
            raise ValueError(f"{where}: frame range {value!r} is empty (A:B is half-open, B must exceed A)")
    raise ValueError(f"{where}: frames must be A:B, N or a list of frame numbers; got {value!r}")


def load_graph(path: str | Path, overrides: list[str] = (), frames: str | None = None) -> Graph:
    """Read and validate a graph file. Raises GraphError listing every problem found."""
    path = Path(path)
    where = str(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise GraphError([f"{where}: graph file not found"]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise GraphError([f"{where}: cannot read graph file ({exc})"]) from None
    data, problems = parse_yaml(text, where)
    if not isinstance(data, dict):
        raise GraphError(problems + [f"{where}:1: a graph file is a mapping with 'nodes:' (and optional 'frames:', 'defaults:')"])
    return _validate(path.resolve(), where, data, problems, list(overrides), frames)


def _validate(path: Path, where: str, data: _Map, problems: list[str], overrides: list[str], frames_arg) -> Graph:
    def at(line) -> str:
        return f"{where}:{line}"

    reg = registry()
    for k in data:
        if k not in TOP_KEYS:
            problems.append(f"{at(data.lines[k])}: unknown top-level key '{k}'{suggest(k, TOP_KEYS)}")

    frames = [0]
    try:
        if frames_arg is not None:
            frames = parse_frames(frames_arg, "--frames")
        elif "frames" in data:
            frames = parse_frames(data["frames"], at(data.lines["frames"]))
    except ValueError as exc:
        problems.append(str(exc))

    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        problems.append(f"{at(data.lines['defaults'])}: 'defaults' must map node types to parameter mappings")
        defaults = {}
    for t, ps in defaults.items():
        line = defaults.lines[t]
        if not isinstance(t, str) or t not in reg:
            problems.append(f"{at(line)}: defaults: unknown node type '{t}'{suggest(t, reg)}")
        elif not isinstance(ps, dict):
            problems.append(f"{at(line)}: defaults for '{t}' must be a mapping of parameters")
        else:
            for p in ps:
                if p not in reg[t].params:
                    problems.append(f"{at(ps.lines[p])}: defaults: node type '{t}' has no parameter '{p}'{suggest(p, reg[t].params)}")

    raw_nodes = data.get("nodes")
    if not isinstance(raw_nodes, dict) or not raw_nodes:
        line = data.lines.get("nodes", getattr(data, "line", 1))
        problems.append(f"{at(line)}: 'nodes:' must be a non-empty mapping of node name -> {{type, in, params}}")
        raise GraphError(problems)

    # --set overrides: node.param=value
    sets: dict[tuple[str, str], tuple[object, str]] = {}
    for ov in overrides:
        m = re.fullmatch(r"([A-Za-z_][A-Za-z0-9_]*)\.([A-Za-z_][A-Za-z0-9_]*)=(.*)", ov, re.S)
        if not m:
            problems.append(f"--set {ov}: expected NODE.PARAM=VALUE")
            continue
        try:
            value, _ = parse_yaml(m.group(3), f"--set {ov}")
        except GraphError as exc:
            problems.extend(exc.problems)
            continue
        sets[(m.group(1), m.group(2))] = (value, f"--set {ov}")

    nodes: dict[str, NodeSpec] = {}
    for name, entry in raw_nodes.items():
        line = raw_nodes.lines[name]
        if not isinstance(name, str):  # YAML reads on/off/yes/no/true/null/1 as non-strings
            problems.append(f"{at(line)}: node name {name!r} is read by YAML as {type(name).__name__}: quote it or "
                            "use letters, digits and '_'")
            continue
        if not NAME_RE.match(name):
            problems.append(f"{at(line)}: node name '{name}' must be letters, digits and '_' (it is used as NAME.port)")
            continue
        if not isinstance(entry, dict):
            problems.append(f"{at(line)}: node '{name}' must be a mapping with 'type:' (and 'in:', 'params:')")
            continue
        for k in entry:
            if k not in NODE_KEYS:
                problems.append(f"{at(entry.lines[k])}: node '{name}': unknown key '{k}'{suggest(k, NODE_KEYS)}")
        t = entry.get("type")
        if t is None:
            problems.append(f"{at(line)}: node '{name}' has no 'type:'")
            continue
        if not isinstance(t, str) or t not in reg:
            problems.append(f"{at(entry.lines['type'])}: node '{name}': unknown node type '{t}'{suggest(t, reg)}")
            continue
        cls = reg[t]
        spec = NodeSpec(name, t, cls, {}, {}, line)
        if "keep" in entry:  # checkpoints: true (every output) or a list of output ports
            keep, kline = entry["keep"], at(entry.lines["keep"])
            if keep is True:
                spec.keep = tuple(cls.outputs)
            elif keep is False or keep is None:
                spec.keep = ()
            elif isinstance(keep, list) and all(isinstance(k, str) for k in keep):
                bad = [k for k in keep if k not in cls.outputs]
                for k in bad:
                    problems.append(f"{kline}: node '{name}': keep: type '{t}' has no output '{k}'{suggest(k, cls.outputs)}")
                spec.keep = tuple(k for k in keep if k in cls.outputs)
            else:
                problems.append(f"{kline}: node '{name}': keep must be true, false or a list of output ports, got {keep!r}")
        # parameters: declaration default < graph defaults < node params < --set
        given = entry.get("params") or {}
        if not isinstance(given, dict):
            problems.append(f"{at(entry.lines['params'])}: node '{name}': 'params' must be a mapping")
            given = _Map()
            given.lines = {}
        for p in given:
            if p not in cls.params:
                problems.append(f"{at(given.lines[p])}: node '{name}': unknown parameter '{p}' for type '{t}'{suggest(p, cls.params)}")
        for (n, p), (_, label) in sets.items():
            if n == name and p not in cls.params:
                problems.append(f"{label}: node '{name}': unknown parameter '{p}'{suggest(p, cls.params)}")
        tdefaults = defaults.get(t) if isinstance(defaults.get(t), dict) else {}
        for p, decl in cls.params.items():
            if (name, p) in sets:
                value, label = sets[(name, p)]
            elif p in given:
                value, label = given[p], at(given.lines[p])
            elif p in tdefaults:
                value, label = tdefaults[p], at(tdefaults.lines[p])
            elif decl.default is REQUIRED:
                problems.append(f"{at(line)}: node '{name}': parameter '{p}' is required ({decl.describe_type()}: {decl.doc})")
                continue
            else:
                spec.params[p] = decl.default
                continue
            spec.lines[f"param:{p}"] = label
            try:
                v = decl.coerce(value)
                if decl.type is InPath and v is not None:
                    resolved = expand_path(v, path.parent)
                    if not resolved.exists():
                        raise ValueError(f"path not found: {resolved}")
                    v = InPath(str(resolved))
                spec.params[p] = v
            except ValueError as exc:
                problems.append(f"{label}: node '{name}': parameter '{p}' {exc}")
        # inputs
        conns = entry.get("in") or {}
        if not isinstance(conns, dict):
            problems.append(f"{at(entry.lines['in'])}: node '{name}': 'in' must map input ports to NODE.PORT")
            conns = {}
        for port, src in conns.items():
            pline = at(conns.lines[port])
            spec.lines[f"in:{port}"] = pline
            if port not in cls.inputs:
                problems.append(f"{pline}: node '{name}': type '{t}' has no input '{port}'{suggest(port, cls.inputs)}")
                continue
            if not (isinstance(src, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*\.[A-Za-z_][A-Za-z0-9_]*", src)):
                problems.append(f"{pline}: node '{name}': input '{port}' must be NODE.PORT, got {src!r}")
                continue
            spec.inputs[port] = tuple(src.split("."))
        nodes[name] = spec

    for (n, _p), (_, label) in sets.items():
        if n not in raw_nodes:
            problems.append(f"{label}: no node named '{n}'{suggest(n, raw_nodes)}")

    # edges: sources exist, ports exist, types match, required inputs connected
    upstream: dict[str, list[str]] = {n: [] for n in nodes}
    for name, spec in nodes.items():
        for port, (src, sport) in spec.inputs.items():
            pline = spec.lines[f"in:{port}"]
            want = spec.cls.inputs[port].type
            if src not in raw_nodes:
                problems.append(f"{pline}: node '{name}': input '{port}' refers to unknown node '{src}'{suggest(src, raw_nodes)}")
                continue
            if src not in nodes:
                continue  # that node had its own error
            outs = nodes[src].cls.outputs
            if sport not in outs:
                problems.append(f"{pline}: node '{name}': input '{port}': node '{src}' ({nodes[src].type_name}) has no output '{sport}'{suggest(sport, outs)}")
                continue
            have = outs[sport].type
            if not compatible(have, want):
                problems.append(f"{pline}: node '{name}': input '{port}' expects {describe_type(want)} but '{src}.{sport}' is {describe_type(have)}")
                continue
            if src not in upstream[name]:
                upstream[name].append(src)
        for port, inp in spec.cls.inputs.items():
            if not inp.optional and port not in spec.inputs:
                problems.append(f"{at(spec.line)}: node '{name}': required input '{port}' ({describe_type(inp.type)}) is not connected")
    cycle = find_cycle(upstream)
    if cycle:
        problems.append(f"{at(nodes[cycle[0]].line)}: cycle in the graph: {' -> '.join(cycle + [cycle[0]])}")
    if problems:
        raise GraphError(problems)
    return Graph(path, frames, nodes, upstream, str(data.get("description", "")), list(overrides))


def topological_order(upstream: dict[str, list[str]], pos: dict[str, int]) -> list[str] | None:
    """Nodes in dependency order, the earliest in ``pos`` first among those ready (None when there is a cycle)."""
    import heapq

    waiting = {n: len(set(u)) for n, u in upstream.items()}
    down: dict[str, list[str]] = {n: [] for n in upstream}
    for n, ups in upstream.items():
        for u in set(ups):
            down[u].append(n)
    ready = [(pos[n], n) for n, k in waiting.items() if k == 0]
    heapq.heapify(ready)
    order = []
    while ready:
        _, n = heapq.heappop(ready)
        order.append(n)
        for d in down[n]:
            waiting[d] -= 1
            if waiting[d] == 0:
                heapq.heappush(ready, (pos[d], d))
    return order if len(order) == len(upstream) else None


def find_cycle(upstream: dict[str, list[str]]) -> list[str]:
    """One cycle as a list of nodes, each feeding the next (and the last the first), or [] when there is none."""
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    for start in upstream:
        if state.get(start):
            continue
        path, stack = [], [(start, iter(upstream[start]))]
        state[start] = 1
        path.append(start)
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                state[node] = 2
                stack.pop()
                path.pop()
            elif state.get(nxt) == 1:
                cyc = path[path.index(nxt):][::-1]  # the path runs downstream -> upstream; a cycle reads along the flow
                order = list(upstream)
                first = min(range(len(cyc)), key=lambda i: order.index(cyc[i]))  # start at the earliest in the file
                return cyc[first:] + cyc[:first]
            elif not state.get(nxt):
                state[nxt] = 1
                path.append(nxt)
                stack.append((nxt, iter(upstream[nxt])))
    return []
