"""Hostile graph files, --set values and command lines for the fuzz test (tests/engine/test_fuzz.py) and the
long run (tests/fuzz/run_fuzz.py): hypothesis strategies and a fixed catalogue of attacks, plus `attempt`,
which runs one case through the command line in this process and classifies the outcome.

Outcome of a case: "ok" (exit 0), "clean" (exit 2 with a message and no traceback), "node failed" (`run`
exit 1: a work item failed with a one-line message, e.g. a test node reading a folder as a file), "traceback" (an exception
escaped, a traceback was printed, another exit code, or exit 2 without a message), "slow" (over the case's
time limit). Hangs are caught by the caller (the long run kills a worker that does not answer in time; the
suite arms faulthandler).
"""
from __future__ import annotations

import contextlib
import io
import os
import string
import time
import traceback
from pathlib import Path

import yaml
from hypothesis import strategies as st

TOP = ["frames", "defaults", "nodes", "description"]
NODE_KEYS = ["type", "in", "params", "doc"]
HOSTILE_SNIPPETS = ["\x00", "\x07", "\x1b[31m", "\ufeff", "\r", "\t", "\u2028", "\ud7ff", "&a ", "*a", "*b", "&b [*a, *a]",
                    "[" * 40, "{" * 40, "]", "}", ": ", "- ", "? ", "!!python/object/apply:os.system ['true']",
                    "!!binary AAAA", "%YAML 1.1\n", "---\n", "...\n", "'", '"', "#", "|\n", ">\n", "<<: *a",
                    "${HOME}", "${UNSET_VAR_XYZ}", "../" * 20, "/dev/zero", "9" * 400, "-0x1p9999", ".nan", ".inf",
                    "~", "null", "on", "yes", "1:", ":1", "0:99999999999", "\\", "é", "\U0001F600"]


def node_vocabulary():
    """Node types with their parameter and port names, from the registry (engine test nodes included)."""
    from nodegraph.node import registry

    reg = registry()
    types = sorted(reg)
    params = sorted({p for c in reg.values() for p in c.params})
    ports = sorted({p for c in reg.values() for p in list(c.inputs) + list(c.outputs)})
    return types, params, ports


def strategies():
    """(graph text strategy, --set list strategy)."""
    types, params, ports = node_vocabulary()
    names = st.one_of(st.sampled_from(["a", "b", "src", "hull", "mesh", "m2", "on", "null", "1", "x_y"]),
                      st.text(string.ascii_letters + "_\n. -", min_size=1, max_size=8))
    words = st.one_of(st.sampled_from(TOP + NODE_KEYS + types + params + ports), names)
    scalar = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(), st.text(max_size=12), words,
                       st.sampled_from(["0:3", "5:2", "-3:0", "a.out", "src.out", "b.x", ".", "..", "/", "${HOME}",
                                        "${NOPE_VAR}", "mesh_{frame:04d}.ply", "{camera}/{frame}", "/etc/passwd"]))
    value = st.recursive(scalar, lambda ch: st.lists(ch, max_size=4) | st.dictionaries(words, ch, max_size=4),
                         max_leaves=12)
    conn = st.one_of(st.builds(lambda n, p: f"{n}.{p}", names, st.sampled_from(ports)), value)
    entry = st.one_of(st.fixed_dictionaries({"type": st.one_of(st.sampled_from(types), value)},
                                            optional={"in": st.dictionaries(st.one_of(st.sampled_from(ports), words), conn, max_size=3),
                                                      "params": st.dictionaries(st.one_of(st.sampled_from(params), words), value, max_size=3),
                                                      "doc": value}), value)
    doc = st.fixed_dictionaries({"nodes": st.one_of(st.dictionaries(names, entry, min_size=1, max_size=4), value)},
                                optional={"frames": value, "defaults": st.dictionaries(st.one_of(st.sampled_from(types), words),
                                                                                       st.dictionaries(words, value, max_size=2), max_size=2),
                                          "description": value, "extra": value})
    long_text = st.builds(lambda ch, n: ch * n, st.sampled_from(["x", "[", "9", "\u00e9"]), st.integers(300, 6000))
    snippet = st.one_of(st.sampled_from(HOSTILE_SNIPPETS), st.text(max_size=6), long_text)
    edits = st.lists(st.tuples(st.floats(0, 1), snippet, st.integers(0, 3)), max_size=3)

    def render(d, ed):
        text = yaml.safe_dump(d, allow_unicode=True, sort_keys=False)
        for where, snippet, cut in ed:
            i = int(where * len(text))
            text = text[:i] + snippet + text[i + cut:]
        return text

    graph = st.builds(render, doc, edits)
    sets = st.lists(st.one_of(st.builds(lambda n, p, v: f"{n}.{p}={v}", names, st.sampled_from(params),
                                        st.one_of(st.text(max_size=20), snippet)),
                              st.text(max_size=20)), max_size=3)
    return graph, sets


def write_case(path: Path, text) -> None:
    """Write the graph file of a case."""
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_bytes(text.encode("utf-8", "surrogatepass"))  # a lone surrogate becomes invalid UTF-8


def attempt(args: list[str], limit: float = 10.0) -> tuple[str, str, float]:
    """Run the command line in this process: (outcome, detail, seconds); see the module docstring."""
    from nodegraph.cli import main

    err, out = io.StringIO(), io.StringIO()
    t0 = time.monotonic()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            rc = main(args)
    except SystemExit as exc:  # argparse
        rc = exc.code if isinstance(exc.code, int) else 2
    except BaseException as exc:  # noqa: BLE001 - what escaped is the finding
        return "traceback", f"{type(exc).__name__}: {exc}"[:300] + "\n" + traceback.format_exc()[-1500:], time.monotonic() - t0
    dt = time.monotonic() - t0
    text = err.getvalue()
    if "Traceback (most recent call last)" in text:
        return "traceback", text[-1500:], dt
    if rc == 1 and "FAILED node" in text:   # a work item failed and said why (its traceback is in its log)
        return "node failed", text[:300], dt
    if rc not in (0, 2):
        return "traceback", f"exit code {rc}: {text[-500:]}", dt
    if dt > limit:
        return "slow", f"{dt:.1f} s", dt
    if rc == 2 and not text.strip():
        return "traceback", "exit 2 without a message", dt
    return ("ok" if rc == 0 else "clean"), text[:300], dt


# ---------------------------------------------------------------- the fixed catalogue (long run)
def _bomb(levels: int, width: int, where: str) -> str:
    lines = [f"x0: &a0 [{', '.join(['lol'] * width)}]"]
    for k in range(1, levels):
        lines.append(f"x{k}: &a{k} [{', '.join([f'*a{k - 1}'] * width)}]")
    last = f"*a{levels - 1}"
    body = {"description": f"description: {last}\nnodes:\n  a: {{type: t.source}}\n",
            "param": f"nodes:\n  a: {{type: t.source, params: {{value: {last}}}}}\n",
            "frames": f"frames: {last}\nnodes:\n  a: {{type: t.source}}\n",
            "type": f"nodes:\n  a: {{type: {last}}}\n",
            "name": f"nodes:\n  ? {last}\n  : {{type: t.source}}\n"}[where]
    return "\n".join(lines) + "\n" + body


VALID = ("frames: 0:3\nnodes:\n  src:   {type: t.source, params: {value: 1.0}}\n"
         "  scale: {type: t.scale, in: {x: src.out}, params: {factor: 3}}\n  plus:  {type: t.add, in: {a: scale.out}}\n"
         "  total: {type: t.total, in: {x: plus.out}}\n  write: {type: t.write, in: {x: plus.out}}\n")


def catalogue(tmp: Path) -> list[tuple[str, object, list[str]]]:
    """(category, graph text or bytes, extra argv) for the long run: about a thousand hostile cases. An argv
    starting with "RUN" runs the graph instead of validating it."""
    from nodegraph.node import registry

    types, params, ports = node_vocabulary()
    reg = registry()
    valid = VALID
    cases: list[tuple[str, object, list[str]]] = []
    # 1. truncations of a valid file at every 3rd character
    for i in range(0, len(valid), 3):
        cases.append(("truncated", valid[:i], []))
    # 2. control characters and odd code points at many positions
    for ch in ["\x00", "\x01", "\x07", "\x08", "\x0b", "\x0c", "\x1b", "\x7f", "\x85", "\ufffe", "\ud800", "\u2028"]:
        for pos in range(7, len(valid), 37):
            cases.append(("control character", valid[:pos] + ch + valid[pos:], []))
    # 3. alias bombs
    for levels in (2, 4, 6, 8, 9, 10):
        for width in (3, 9, 16):
            for where in ("description", "param", "frames", "type", "name"):
                cases.append(("alias bomb", _bomb(levels, width, where), []))
    cases.append(("alias bomb", "description: &r [*r]\nnodes:\n  a: {type: t.source}\n", []))
    cases.append(("alias bomb", "description: &r {a: *r}\nnodes:\n  a: {type: t.source}\n", []))
    # 4. nesting
    for depth in (10, 50, 63, 65, 100, 500, 1000, 2000, 5000, 20000):
        for o, c in (("[", "]"), ("{a: ", "}"), ("- ", "")):
            if o == "- ":
                text = "description:\n" + "".join("  " * i + "- \n" for i in range(min(depth, 3000)))
            else:
                text = "description: " + o * depth + "1" * (o == "[") + c * depth + "\n"
            cases.append(("nesting", text + "nodes:\n  a: {type: t.source}\n", []))
    # 5. huge values and files
    for n in (10**3, 10**5, 3 * 10**5):
        cases.append(("huge", f"description: '{'z' * n}'\nnodes:\n  a: {{type: t.source}}\n", []))
        cases.append(("huge", f"nodes:\n  a: {{type: t.source, params: {{value: '{'9' * n}'}}}}\n", []))
    for n in (10**4, 10**5, 3 * 10**6):
        cases.append(("huge", "frames: [" + ", ".join(map(str, range(n))) + "]\nnodes:\n  a: {type: t.source}\n", []))
    cases.append(("huge", "nodes:\n" + "".join(f"  n{i}: {{type: t.source}}\n" for i in range(5000)), []))
    cases.append(("huge", "frames: 0:1000001\nnodes:\n  a: {type: t.source}\n", []))
    # 6. type confusion at every level
    for w in ["", "~", "1", "-1", "1.5", "true", "[]", "{}", "[1, 2]", "{a: 1}", "'x'", ".nan", "!!binary AAAA", "2001-12-14"]:
        for text in (f"{w}\n", f"nodes: {w}\n", f"frames: {w}\nnodes:\n  a: {{type: t.source}}\n",
                     f"defaults: {w}\nnodes:\n  a: {{type: t.source}}\n",
                     f"defaults: {{t.source: {w}}}\nnodes:\n  a: {{type: t.source}}\n", f"nodes:\n  a: {w}\n",
                     f"nodes:\n  a: {{type: {w}}}\n", f"nodes:\n  a: {{type: t.source, params: {w}}}\n",
                     f"nodes:\n  a: {{type: t.source}}\n  b: {{type: t.scale, in: {w}}}\n",
                     f"nodes:\n  a: {{type: t.source}}\n  b: {{type: t.scale, in: {{x: {w}}}}}\n",
                     f"nodes:\n  ? {w}\n  : {{type: t.source}}\n", f"description: {w}\nnodes:\n  a: {{type: t.source}}\n"):
            cases.append(("type confusion", text, []))
    # 7. every parameter of every node type with hostile values
    hostile_values = ["-1", "0", "1e400", "-1e400", ".nan", ".inf", "99999999999999999999999", "true", "'x'", "[]",
                      "[1, 2, 3, 4, 5, 6]", "{}", "''", '"\\0"', "'${NOPE_VAR_X}'", "'../../../../etc/passwd'", "/",
                      "'" + "p" * 5000 + "'"]
    for t in types:
        for p in reg[t].params:
            for v in hostile_values[:: (1 if t.startswith("t.") else 3)]:
                cases.append(("parameter", f"nodes:\n  a:\n    type: {t}\n    params: {{{p}: {v}}}\n", []))
    # 8. connections
    for src in ("a.out", "a.nope", "nope.out", "a", ".out", "a.", "a.out.x", "b.out", "a.files", "w.files", "'a .out'"):
        cases.append(("connection", f"nodes:\n  a: {{type: t.source}}\n  b: {{type: t.scale, in: {{x: {src}}}}}\n"
                                    f"  w: {{type: t.write, in: {{x: b.out}}}}\n", []))
    cases.append(("connection", "nodes:\n  a: {type: t.scale, in: {x: a.out}}\n", []))
    cases.append(("connection", "nodes:\n  a: {type: t.scale, in: {x: b.out}}\n  b: {type: t.scale, in: {x: c.out}}\n"
                                "  c: {type: t.scale, in: {x: a.out}}\n", []))
    for t in types:
        for port in list(reg[t].inputs)[:3]:
            cases.append(("connection", f"nodes:\n  a: {{type: t.source}}\n  b: {{type: {t}, in: {{{port}: a.out}}}}\n", []))
    # 9. paths
    fifo = tmp / "fifo"
    if not fifo.exists():
        os.mkfifo(fifo)
    folder = tmp / "folder"
    folder.mkdir(exist_ok=True)
    for name, target in (("zeros", "/dev/zero"), ("loop", str(folder)), ("pipe", str(fifo))):
        if not (folder / name).is_symlink():
            os.symlink(target, folder / name)
    for path in (str(fifo), "/dev/zero", "/dev/null", str(folder), "/proc/self/fd/0", "x" * 300, "y/" * 3000,
                 "${NOPE_VAR_Y}", "~nouser/x", "\\\\server\\share", "a\tb", "ü/ß", "/etc/passwd_{frame}", "../up_{frame}"):
        v = yaml.safe_dump(path, width=10**6).splitlines()[0]
        cases.append(("path", f"nodes:\n  r:\n    type: t.readfile\n    params: {{path: {v}}}\n", []))
        cases.append(("path", f"nodes:\n  r:\n    type: t.readdir\n    params: {{path: {v}}}\n", ["RUN"]))
        cases.append(("path", f"nodes:\n  a: {{type: t.source}}\n  w:\n    type: t.write\n    in: {{x: a.out}}\n"
                              f"    params: {{path: {v}}}\n", []))
    # 10. node names
    for nm in ('"m2\\n"', '"a b"', '"ä"', '"1x"', "on", "null", "1", "x" * 100, '"a.b"', '"_"', '"\\t"', "'-'", '"a\\0"'):
        cases.append(("node name", f"nodes:\n  {nm}: {{type: t.source}}\n", []))
    # 11. frames
    for fr in ("0:3", "3:0", "-5:0", "0:0", "[]", "[1, 1, 1]", "[-1, 2]", "[true]", "[1.5]", "'1:2:3'", "2147483648",
               "[2147483648]", "-2147483649", "' 4 '", "'0x10'", "1:20", "0b101", "'٣'", "[0, '1']"):
        cases.append(("frames", f"frames: {fr}\nnodes:\n  a: {{type: t.source}}\n", []))
    # 12. --set values and command-line options
    for s in ["a.value=1", "a.value=\x00", "a.value=\x1b", "a.value=" + "9" * 5000, "a.value=" + "[" * 100, "a.value=*x",
              "a.value=&x [*x]", "a.value=!!python/object/apply:os.system ['true']", "a.nope=1", "b.value=1", "a=1",
              "=1", ".=", "a.value", "a.value=\ud800", "a.size=1e400", "a.size=-0", "a.value=.nan", "a.value='\n'",
              "a.b.c=1", "A.value=1", "a.value=" + "[" * 3000, "a.value=" + "9" * 100_000]:
        cases.append(("--set", "nodes:\n  a: {type: t.source}\n", ["--set", s]))
    for opts in (["--frames", "5:2"], ["--frames", "x"], ["--frames", "0:99999999999"], ["--jobs", "0"], ["--jobs", "-3"],
                 ["--jobs", "abc"], ["--executor", "nope"], ["--executor", "dask", "--scheduler", "garbage"],
                 ["--scheduler", "tcp://1.2.3.4:5"], ["--workers", "2"], ["--device", "nonsense"], ["--device", "9:9"],
                 ["--out", "/dev/null/x"], ["--out", str(fifo)], ["--out", "/proc/forbidden"]):
        cases.append(("options", valid, ["RUN"] + opts))
    # 13. YAML tags that would execute code or build objects
    for tag in ("!!python/object/apply:os.system ['touch /tmp/volcap_pwned']", "!!python/name:os.system",
                "!!python/object:object {}", "!!set {a, b}", "!!omap [a: 1]", "!!timestamp 2001-12-14", "!!float nan",
                "!!int 0o17", "!custom x"):
        cases.append(("yaml tag", f"description: {tag}\nnodes:\n  a: {{type: t.source}}\n", []))
        cases.append(("yaml tag", f"nodes:\n  a: {{type: t.source, params: {{value: {tag}}}}}\n", []))
    # 14. encodings
    for raw in (b"\xff\xfenodes:\n", b"nodes:\n  a: {type: t.source}\n\xc3\x28\n", b"\x00" * 100, bytes(range(256)),
                "nodes:\n  a: {type: t.source}\n".encode("utf-16")):
        cases.append(("encoding", raw, []))
    return cases
