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
import graphlib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .errors import GraphError
from .node import REQUIRED, InPath, Node, OutPath, registry, show
from .types import compatible, describe_type

MAX_FRAMES = 1_000_000  # a range beyond this is a typo, not a capture
MAX_FRAME_NUMBER = 2**31 - 1
MAX_FILE_BYTES = 1 << 20     # a graph file is a few kilobytes; a megabyte is not a graph, it is an accident
MAX_SET_CHARS = 1 << 16      # one --set value
MAX_VALUES = 1_000_000       # values in the document once YAML aliases are expanded (alias bombs)
MAX_DEPTH = 64               # nesting of lists and mappings
MAX_PATH_CHARS = 4096
MAX_NAME_CHARS = 64          # node names (they name log files and folders)
MAX_NAME_BYTES = 255         # one path component
TOP_KEYS = ("frames", "defaults", "nodes", "description")
NODE_KEYS = ("type", "in", "params", "keep", "window", "doc")
NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")   # used with fullmatch ('$' also matches before a final newline)
# what YAML allows in a document (yaml.reader.Reader.NON_PRINTABLE): tab, newlines and printable characters
NON_PRINTABLE = re.compile("[^\x09\x0A\x0D\x20-\x7E\x85\xA0-\uD7FF\uE000-\uFFFD\U00010000-\U0010ffff]")

def q(value) -> str:
    """A user's key, name or type for a message between quotes: text cleaned, anything else shown."""
    return clean(value) if isinstance(value, str) else show(value)


def clean(text: str, limit: int = 120) -> str:
    """Text from the user (a --set argument, a key) for a message: control characters escaped, cut short."""
    text = str(text)
    cut = text[:limit]
    out = NON_PRINTABLE.sub(lambda m: m.group(0).encode("unicode_escape").decode("ascii"), cut)
    return out + (f"... ({len(text)} characters)" if len(text) > limit else "")


class _Map(dict):
    """A mapping that remembers the line of each key (1-based) and its own line."""

    line: int = 0
    lines: dict


# libyaml (when PyYAML has it) parses ~10x faster than the pure-Python parser: a 1 MB file in well under a
# second. Its composer recurses in C, so nesting is bounded from the event stream first (_check_depth).
_BaseLoader = yaml.CSafeLoader if getattr(yaml, "__with_libyaml__", False) else yaml.SafeLoader


class _Loader(_BaseLoader):
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


def _check_characters(text: str, where: str):
    m = NON_PRINTABLE.search(text)
    if m:
        line = text.count("\n", 0, m.start()) + 1
        col = m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
        raise GraphError([f"{where}:{line}:{col}: character U+{ord(m.group(0)):04X} is not allowed in YAML "
                          "(a control character or NUL: is this a text file?)"])


def _check_tree(root, where: str):
    """Refuse documents whose aliases expand beyond MAX_VALUES values, that nest deeper than MAX_DEPTH or
    that refer to themselves: the composed node graph is walked once, shared (aliased) nodes counted once
    with their expanded size."""
    size: dict[int, int] = {}
    height: dict[int, int] = {}
    active: set[int] = set()
    stack = [(root, False)]

    def children(node):
        if isinstance(node, yaml.SequenceNode):
            return node.value
        if isinstance(node, yaml.MappingNode):
            return [x for kv in node.value for x in kv]
        return []

    def at(node) -> str:
        return f"{where}:{node.start_mark.line + 1}"

    while stack:
        node, done = stack.pop()
        nid = id(node)
        if done:
            active.discard(nid)
            kids = children(node)
            size[nid] = 1 + sum(size[id(k)] for k in kids)
            height[nid] = 1 + max((height[id(k)] for k in kids), default=0)
            if size[nid] > MAX_VALUES:
                raise GraphError([f"{at(node)}: YAML aliases expand this value to more than {MAX_VALUES:,} values "
                                  "(an alias bomb?); write it out, or use fewer aliases"])
            if height[nid] > MAX_DEPTH:
                raise GraphError([f"{at(node)}: lists and mappings nested more than {MAX_DEPTH} deep"])
            continue
        if nid in size:
            continue
        if nid in active:
            raise GraphError([f"{at(node)}: a YAML alias refers to the value that contains it (recursive alias)"])
        active.add(nid)
        stack.append((node, True))
        if len(active) > MAX_DEPTH + 1:
            raise GraphError([f"{at(node)}: lists and mappings nested more than {MAX_DEPTH} deep"])
        stack.extend((k, False) for k in children(node) if id(k) not in size)


def _check_depth(text: str, where: str):
    """Refuse nesting deeper than MAX_DEPTH from the parser's event stream (iterative), before anything
    recursive (the composer, repr, json) sees the document; and numbers too long to convert."""
    pre = _BaseLoader(text)
    try:
        depth = 0
        while True:
            ev = pre.get_event()
            if ev is None:
                break
            if isinstance(ev, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise GraphError([f"{where}:{ev.start_mark.line + 1}: lists and mappings nested more than "
                                      f"{MAX_DEPTH} deep"])
            elif isinstance(ev, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                depth -= 1
            elif isinstance(ev, yaml.ScalarEvent) and len(ev.value) > 4000 and not ev.style and \
                    re.fullmatch(r"[-+]?[0-9_]+", ev.value):
                raise GraphError([f"{where}:{ev.start_mark.line + 1}: a number with {len(ev.value):,} digits "
                                  "(quote it if it is text)"])
    finally:
        pre.dispose()


def parse_yaml(text: str, where: str, limit: int = MAX_FILE_BYTES):
    """(data, problems) of a YAML document; GraphError for what cannot be read: syntax, characters YAML does
    not allow, alias bombs, nesting beyond MAX_DEPTH, more than ``limit`` characters."""
    if len(text) > limit:
        raise GraphError([f"{where}: too large ({len(text):,} characters; a graph file or value has at most {limit:,})"])
    _check_characters(text, where)
    loader = None
    try:
        _check_depth(text, where)
        loader = _Loader(text)
        loader.duplicate_keys = []
        node = loader.get_single_node()
        if node is None:
            data = None
        else:
            _check_tree(node, where)
            data = loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        if "nesting depth" in str(exc.problem):  # libyaml's own limit (PyYAML >= 6.0.4), met scanning ahead of _check_depth
            raise GraphError([f"{where}:{mark.line + 1 if mark else '?'}: lists and mappings nested more than "
                              f"{MAX_DEPTH} deep"]) from None
        line = f"{mark.line + 1}:{mark.column + 1}" if mark else "?"
        raise GraphError([f"{where}:{line}: YAML syntax error: {clean(exc.problem or exc, 300)}"]) from None
    except yaml.YAMLError as exc:
        raise GraphError([f"{where}: YAML error: {clean(exc, 300)}"]) from None
    except RecursionError:
        line = getattr(loader, "line", 0) + 1
        raise GraphError([f"{where}:{line}: lists and mappings nested too deeply (more than {MAX_DEPTH})"]) from None
    except (ValueError, OverflowError, TypeError) as exc:  # a constructor refusing a value (int digit limit ...)
        raise GraphError([f"{where}: a value cannot be read: {clean(exc, 200)}"]) from None
    finally:
        if loader is not None:
            loader.dispose()
    problems = [f"{where}:{line}: duplicate key {show(k)}" for line, k in loader.duplicate_keys]
    return data, problems


def suggest(word: str, options) -> str:
    if not isinstance(word, (str, int, float)) or len(str(word)) > 100:
        return ""
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def check_path_length(text: str):
    """ValueError when a path cannot exist on any file system we run on (too long, a name over 255 bytes)."""
    if len(text) > MAX_PATH_CHARS:
        raise ValueError(f"is too long as a path ({len(text):,} characters; at most {MAX_PATH_CHARS})")
    for part in re.split(r"[/\\]", text):
        if len(part.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES:
            raise ValueError(f"has a file or folder name that is too long ({len(part):,} characters; at most "
                             f"{MAX_NAME_BYTES} bytes): {clean(part, 40)}")


def check_out_path(text: str):
    """ValueError unless ``text`` is a relative path that stays inside the output folder."""
    check_path_length(text)
    if "\x00" in text:
        raise ValueError("contains a NUL character")
    parts = re.split(r"[/\\]", text)
    if text.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", text) or os.path.isabs(text):
        raise ValueError(f"must be relative to the output folder, got {show(text)}")
    if ".." in parts:
        raise ValueError(f"must stay inside the output folder (no '..'), got {show(text)}")
    if not text.strip() or not parts[-1].strip():
        raise ValueError(f"must name a file, got {show(text)}")


def _input_path(value: str, base: Path) -> Path:
    """An input path parameter expanded and resolved; ValueError unless it names an existing regular file or
    folder (a FIFO or a device would block or never end when read)."""
    check_path_length(value)
    if not value.strip():
        raise ValueError("must not be empty (it would name the graph file's own folder)")
    try:
        resolved = expand_path(value, base)
    except OSError as exc:
        raise ValueError(f"cannot be used as a path ({exc.strerror or exc})") from None
    check_path_length(str(resolved))
    if len(resolved.parts) > 1 and resolved.parts[1] in ("proc", "sys", "dev"):
        raise ValueError(f"lies in the system folder /{resolved.parts[1]}, which holds no data: {clean(resolved, 200)}")
    try:
        if not resolved.exists():
            raise ValueError(f"path not found: {clean(resolved, 300)}")
        if not (resolved.is_file() or resolved.is_dir()):
            raise ValueError(f"is not a regular file or folder (a FIFO, socket or device?): {clean(resolved, 300)}")
    except OSError as exc:
        raise ValueError(f"cannot be used as a path ({exc.strerror or exc}): {clean(resolved, 300)}") from None
    return resolved


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
    window: int = 0                    # a sequence node's frames per work item (0: one item over all frames)


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


def coerce_param(decl, value, base: Path):
    """A parameter value as run() receives it: coerced to its declared type; an input path expanded and resolved
    against ``base`` (it must exist), an output path checked to stay in the output folder. ValueError saying
    what is wrong."""
    v = decl.coerce(value)
    if decl.type is InPath and v is not None:
        v = InPath(str(_input_path(v, base)))
    elif decl.type is OutPath and v is not None:
        check_out_path(v)
    return v


def parse_frames(value, where: str) -> list[int]:
    def checked(frames: list[int]) -> list[int]:
        if frames and max(abs(frames[0]), abs(frames[-1])) > MAX_FRAME_NUMBER:
            raise ValueError(f"{where}: frame numbers must lie within ±{MAX_FRAME_NUMBER}; got {show(value)}")
        return frames

    if isinstance(value, bool):
        raise ValueError(f"{where}: frames must be A:B, N or a list of frame numbers; got {show(value)}")
    if isinstance(value, int):
        return checked([value])
    if isinstance(value, list) and len(value) > MAX_FRAMES:
        raise ValueError(f"{where}: the frames list has {len(value):,} entries (at most {MAX_FRAMES:,})")
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return checked(sorted(set(value)))
    if isinstance(value, str) and len(value) < 100 and re.fullmatch(r"\s*-?\d+\s*", value):
        return checked([int(value)])
    if isinstance(value, str) and len(value) < 100:
        m = re.fullmatch(r"\s*(-?\d+)\s*:\s*(-?\d+)\s*", value)
        if m:
            a, b = int(m.group(1)), int(m.group(2))
            if b - a > MAX_FRAMES:
                raise ValueError(f"{where}: frame range {show(value)} has {b - a} frames (at most {MAX_FRAMES})")
            if b > a:
                return checked([a, b - 1]) and list(range(a, b))
            raise ValueError(f"{where}: frame range {show(value)} is empty (A:B is half-open, B must exceed A)")
    raise ValueError(f"{where}: frames must be A:B, N or a list of frame numbers; got {show(value)}")


def load_graph(path: str | Path, overrides: list[str] = (), frames: str | None = None) -> Graph:
    """Read and validate a graph file. Raises GraphError listing every problem found."""
    path = Path(path)
    where = clean(path, 300)
    try:
        st = path.stat()
        if not path.is_file():   # a folder, a FIFO or a device would block or never end
            raise GraphError([f"{where}: not a regular file"])
        if st.st_size > MAX_FILE_BYTES:
            raise GraphError([f"{where}: too large ({st.st_size:,} bytes; a graph file has at most {MAX_FILE_BYTES:,})"])
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise GraphError([f"{where}: graph file not found"]) from None
    except UnicodeDecodeError as exc:
        raise GraphError([f"{where}: not UTF-8 text (byte {exc.start}: {exc.reason})"]) from None
    except OSError as exc:
        raise GraphError([f"{where}: cannot read graph file ({exc.strerror or exc})"]) from None
    data, problems = parse_yaml(text, where)
    if not isinstance(data, dict):
        raise GraphError(problems + [f"{where}:1: a graph file is a mapping with 'nodes:' (and optional 'frames:', 'defaults:')"])
    return _validate(path.resolve(), where, data, problems, list(overrides), frames)


def windows(frames: list[int], n: int) -> list[list[int]]:
    """A sequence node's work items: ``frames`` in consecutive runs of ``n`` (the last may be shorter); n = 0: one."""
    return [list(frames[i:i + n]) for i in range(0, len(frames), n)] if n else [list(frames)]


def count_windows(length: int, n: int) -> int:
    return -(-length // n) if n and length else 1


def cut_window(length: int, n_src: int, n_dst: int) -> tuple[int, int] | None:
    """The first window of ``n_src`` frames (positions start, stop) that a reader's windows of ``n_dst`` frames cut
    (a reader window boundary strictly inside it), or None: arithmetic on the positions, no lists of frames."""
    if not n_dst or n_dst >= length:
        return None
    if not n_src:
        return (0, length)
    import numpy as np

    start = np.arange(0, length, n_src)
    stop = np.minimum(start + n_src, length)
    boundary = (start // n_dst + 1) * n_dst          # the first reader boundary after each window's start
    hit = np.flatnonzero(boundary < stop)
    return (int(start[hit[0]]), int(stop[hit[0]])) if len(hit) else None


def _validate(path: Path, where: str, data: _Map, problems: list[str], overrides: list[str], frames_arg) -> Graph:
    def at(line) -> str:
        return f"{where}:{line}"

    reg = registry()
    for k in data:
        if k not in TOP_KEYS:
            problems.append(f"{at(data.lines[k])}: unknown top-level key '{q(k)}'{suggest(k, TOP_KEYS)}")

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
            problems.append(f"{at(line)}: defaults: unknown node type '{q(t)}'{suggest(t, reg)}")
        elif not isinstance(ps, dict):
            problems.append(f"{at(line)}: defaults for '{t}' must be a mapping of parameters")
        else:
            for p in ps:
                if p not in reg[t].params:
                    problems.append(f"{at(ps.lines[p])}: defaults: node type '{t}' has no parameter '{q(p)}'{suggest(p, reg[t].params)}")

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
            problems.append(f"--set {clean(ov)}: expected NODE.PARAM=VALUE")
            continue
        try:
            value, _ = parse_yaml(m.group(3), f"--set {clean(ov)}", MAX_SET_CHARS)
        except GraphError as exc:
            problems.extend(exc.problems)
            continue
        sets[(m.group(1), m.group(2))] = (value, f"--set {clean(ov)}")

    nodes: dict[str, NodeSpec] = {}
    for name, entry in raw_nodes.items():
        line = raw_nodes.lines[name]
        if not isinstance(name, str):  # YAML reads on/off/yes/no/true/null/1 as non-strings
            problems.append(f"{at(line)}: node name {show(name)} is read by YAML as {type(name).__name__}: quote it or "
                            "use letters, digits and '_'")
            continue
        if not NAME_RE.fullmatch(name) or len(name) > MAX_NAME_CHARS:
            problems.append(f"{at(line)}: node name {show(name)} must be letters, digits and '_' (it is used as NAME.port), at most {MAX_NAME_CHARS}")
            continue
        if not isinstance(entry, dict):
            problems.append(f"{at(line)}: node '{name}' must be a mapping with 'type:' (and 'in:', 'params:')")
            continue
        for k in entry:
            if k not in NODE_KEYS:
                problems.append(f"{at(entry.lines[k])}: node '{name}': unknown key '{q(k)}'{suggest(k, NODE_KEYS)}")
        t = entry.get("type")
        if t is None:
            problems.append(f"{at(line)}: node '{name}' has no 'type:'")
            continue
        if not isinstance(t, str) or t not in reg:
            problems.append(f"{at(entry.lines['type'])}: node '{name}': unknown node type '{q(t)}'{suggest(t, reg)}")
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
                    problems.append(f"{kline}: node '{name}': keep: type '{t}' has no output '{q(k)}'{suggest(k, cls.outputs)}")
                spec.keep = tuple(k for k in keep if k in cls.outputs)
            else:
                problems.append(f"{kline}: node '{name}': keep must be true, false or a list of output ports, got {show(keep)}")
        window = sets.pop((name, "window"), None) if "window" not in cls.params else None
        if window is not None or "window" in entry:  # a sequence node split into work items of N frames
            value, wline = window if window is not None else (entry["window"], at(entry.lines["window"]))
            if cls.per != "sequence":
                problems.append(f"{wline}: node '{name}': window applies to sequence nodes; type '{t}' runs per frame")
            elif cls.publishes:
                problems.append(f"{wline}: node '{name}': type '{t}' writes files: its windows would overwrite each other's")
            elif isinstance(value, bool) or not isinstance(value, int) or value < 0:
                problems.append(f"{wline}: node '{name}': window must be a whole number of frames >= 1 (0: all frames), "
                                f"got {show(value)}")
            else:
                spec.window = value
        # parameters: declaration default < graph defaults < node params < --set
        given = entry.get("params") or {}
        if not isinstance(given, dict):
            problems.append(f"{at(entry.lines['params'])}: node '{name}': 'params' must be a mapping")
            given = _Map()
            given.lines = {}
        for p in given:
            if p not in cls.params:
                problems.append(f"{at(given.lines[p])}: node '{name}': unknown parameter '{q(p)}' for type '{t}'{suggest(p, cls.params)}")
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
                spec.params[p] = coerce_param(decl, value, path.parent)
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
                problems.append(f"{pline}: node '{name}': type '{t}' has no input '{q(port)}'{suggest(port, cls.inputs)}")
                continue
            if not (isinstance(src, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*\.[A-Za-z_][A-Za-z0-9_]*", src)):
                problems.append(f"{pline}: node '{name}': input '{port}' must be NODE.PORT, got {show(src)}")
                continue
            spec.inputs[port] = tuple(src.split("."))
        nodes[name] = spec

    for (n, _p), (_, label) in sets.items():
        if n not in raw_nodes:
            problems.append(f"{label}: no node named '{q(n)}'{suggest(n, raw_nodes)}")

    # edges: sources exist, ports exist, types match, required inputs connected
    upstream: dict[str, list[str]] = {n: [] for n in nodes}
    for name, spec in nodes.items():
        for port, (src, sport) in spec.inputs.items():
            pline = spec.lines[f"in:{port}"]
            want = spec.cls.inputs[port].type
            if src not in raw_nodes:
                problems.append(f"{pline}: node '{name}': input '{port}' refers to unknown node '{q(src)}'{suggest(src, raw_nodes)}")
                continue
            if src not in nodes:
                continue  # that node had its own error
            outs = nodes[src].cls.outputs
            if sport not in outs:
                problems.append(f"{pline}: node '{name}': input '{port}': node '{src}' ({nodes[src].type_name}) has no output '{q(sport)}'{suggest(sport, outs)}")
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
    for name, spec in nodes.items():   # a sequence node reading a windowed one: whole windows, joined by their type
        if spec.cls.per != "sequence":
            continue
        for port, (src, sport) in spec.inputs.items():
            if src not in nodes or nodes[src].cls.per != "sequence" or sport not in nodes[src].cls.outputs:
                continue
            n_src, pline = nodes[src].window, spec.lines[f"in:{port}"]
            cut = cut_window(len(frames), n_src, spec.window)
            if cut is not None and not n_src:
                problems.append(f"{pline}: node '{name}': input '{port}': '{src}' covers all frames in one item, more "
                                f"than one of {name}'s windows: window '{src}' too (the same or a divisor), or not '{name}'")
                continue
            if cut is not None:
                problems.append(f"{pline}: node '{name}': input '{port}': '{src}' works in windows "
                                f"({frames[cut[0]]}..{frames[cut[1] - 1]} is one) that {name}'s own windows cut: give "
                                f"'{name}' a window that is a multiple of {n_src}, or none")
                continue
            dtype = nodes[src].cls.outputs[sport].type
            if count_windows(len(frames), n_src) > count_windows(len(frames), spec.window) and getattr(dtype, "join", None) is None:
                problems.append(f"{pline}: node '{name}': input '{port}': '{src}' works in windows of {n_src} frames "
                                f"and {describe_type(dtype)} cannot be joined over windows: read it per frame, or give "
                                f"'{name}' the same window")
    cycle = find_cycle(upstream)
    if cycle:
        problems.append(f"{at(nodes[cycle[0]].line)}: cycle in the graph: {' -> '.join(cycle + [cycle[0]])}")
    if problems:
        raise GraphError(problems)
    return Graph(path, frames, nodes, upstream, str(data.get("description", "")), list(overrides))


def topological_order(upstream: dict[str, list[str]], pos: dict[str, int]) -> list[str] | None:
    """Nodes in dependency order, the earliest in ``pos`` first among those ready (None when there is a cycle).
    ``upstream`` maps each node to the nodes it reads from (graphlib.TopologicalSorter's predecessors)."""
    import heapq

    sorter = graphlib.TopologicalSorter(upstream)
    try:
        sorter.prepare()
    except graphlib.CycleError:
        return None
    ready = [(pos[n], n) for n in sorter.get_ready()]
    heapq.heapify(ready)
    order = []
    while ready:
        _, n = heapq.heappop(ready)
        order.append(n)
        sorter.done(n)
        for d in sorter.get_ready():
            heapq.heappush(ready, (pos[d], d))
    return order


def find_cycle(upstream: dict[str, list[str]]) -> list[str]:
    """One cycle as a list of nodes, each feeding the next (and the last the first), starting at the earliest in
    the file, or [] when there is none."""
    try:
        graphlib.TopologicalSorter(upstream).prepare()
    except graphlib.CycleError as exc:
        cyc = list(exc.args[1][:-1])  # graphlib lists each node before the one it feeds, the first repeated last
        order = list(upstream)
        first = min(range(len(cyc)), key=lambda i: order.index(cyc[i]) if cyc[i] in upstream else len(order))
        return cyc[first:] + cyc[:first]
    return []
