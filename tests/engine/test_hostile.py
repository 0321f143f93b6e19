"""Hostile graph files and command lines (issue 12, items 6, 7, 9): each ends in one clear message and exit
code 2 within a second or two, never a traceback or a hang."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import enginenodes  # registers the t.* nodes

assert enginenodes.Source.type_name == "t.source"
from nodegraph import GraphError
from nodegraph.cli import main as cli
from nodegraph.graphfile import load_graph

HERE = Path(__file__).resolve().parent
OK_GRAPH = "nodes:\n  a: {type: t.source}\n  b: {type: t.scale, in: {x: a.out}}\n"

BOMB = """\
x: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]
y: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]
z: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]
w: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]
v: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]
u: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]
t: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f]
s: &h [*g, *g, *g, *g, *g, *g, *g, *g, *g]
"""


def problems_of(path: Path, **kw) -> list[str]:
    with pytest.raises(GraphError) as exc:
        load_graph(path, **kw)
    return exc.value.problems


def cli_in_subprocess(args: list[str], timeout: float = 60) -> tuple[int, str, float]:
    """Exit code, stderr and seconds of `volcap ARGS` in a fresh process (a hang cannot stall the suite)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    code = f"import sys, enginenodes; from nodegraph.cli import main; sys.exit(main({args!r}))"
    t0 = time.monotonic()
    try:
        p = subprocess.run([sys.executable, "-c", code], env=env, cwd=HERE, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return -1, f"hung for more than {timeout} s", time.monotonic() - t0
    return p.returncode, p.stderr, time.monotonic() - t0


# ---------------------------------------------------------------- item 6: alias bombs
@pytest.mark.parametrize("where", ["description: *h\n", "nodes:\n  a: {type: t.source, params: {value: *h}}\n"])
def test_alias_bomb_is_refused_not_expanded(tmp_path, where):
    p = tmp_path / "g.yaml"
    p.write_text(BOMB + where + ("nodes:\n  a: {type: t.source}\n" if where.startswith("description") else ""))
    rc, err, seconds = cli_in_subprocess(["validate", str(p)], timeout=60)
    assert rc == 2 and "Traceback" not in err, err
    assert f"{p}:" in err and "aliases" in err, err
    assert seconds < 20, seconds


def test_moderate_aliases_still_work(tmp_path):
    p = tmp_path / "g.yaml"
    p.write_text("defaults:\n  t.source: &common {size: 3}\n  t.scale: {factor: 2}\nnodes:\n"
                 "  a: {type: t.source, params: *common}\n  b: {type: t.scale, in: {x: a.out}}\n")
    assert load_graph(p).nodes["a"].params["size"] == 3


def test_recursive_alias_is_one_message(tmp_path):
    p = tmp_path / "g.yaml"
    p.write_text("description: &r [*r]\n" + OK_GRAPH)
    found = problems_of(p)
    assert any(f"{p}:1" in x and "alias" in x for x in found), found


# ---------------------------------------------------------------- item 7: control characters, deep nesting
@pytest.mark.parametrize("text, line", [
    ("nodes:\n  a: {type: t.source}\x00\n", 2),
    ("nodes:\n  a: {type: t.source}\n  b: {type: t.scale, in: {x: a.out}, params: {mode: \"m\x07\"}}\n", 3),
    ("\ufeffnodes:\n  a: {type: t.source}\x1b[31m\n", 2),
])
def test_control_characters_name_file_and_line(tmp_path, capsys, text, line):
    p = tmp_path / "g.yaml"
    p.write_bytes(text.encode())
    found = problems_of(p)
    assert any(x.startswith(f"{p}:{line}:") and "character" in x for x in found), found
    assert cli(["validate", str(p)]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_control_characters_in_set_values(tmp_path, capsys):
    p = tmp_path / "g.yaml"
    p.write_text(OK_GRAPH)
    for value in ("b.mode=\x00", "b.mode=mul\x07", "b.factor=\x1b"):
        found = problems_of(p, overrides=[value])
        assert any(x.startswith("--set b.") and "character" in x for x in found), found
        assert not any(c in "".join(found) for c in "\x00\x07\x1b"), found
        assert cli(["validate", str(p), "--set", value]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and "\x00" not in err and "\x1b" not in err, err


@pytest.mark.parametrize("depth", [200, 3000])
def test_deep_nesting_is_one_message(tmp_path, capsys, depth):
    p = tmp_path / "g.yaml"
    p.write_text("description: " + "[" * depth + "]" * depth + "\n" + OK_GRAPH)
    found = problems_of(p)
    assert any(x.startswith(f"{p}:1") and "nested" in x for x in found), found
    assert cli(["validate", str(p)]) == 2
    assert "Traceback" not in capsys.readouterr().err


# ---------------------------------------------------------------- item 9: command line and values
def test_bad_scheduler_address_is_exit_2(tmp_path, capsys):
    p = tmp_path / "g.yaml"
    p.write_text(OK_GRAPH)
    for args in (["--executor", "dask", "--scheduler", "garbage"], ["--scheduler", "tcp://127.0.0.1:1"]):
        with pytest.raises(SystemExit) as exc:
            cli(["--cache", str(tmp_path / "c"), "run", str(p), "--out", str(tmp_path / "o"), "-q", *args])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "--scheduler" in err and "Traceback" not in err, err


def test_bad_device_is_refused_before_any_work(tmp_path, capsys):
    p = tmp_path / "g.yaml"
    p.write_text(OK_GRAPH)
    for device in ("nonsense", "7:3"):
        rc = cli(["--cache", str(tmp_path / "c"), "run", str(p), "--out", str(tmp_path / "o"), "-q", "-j", "1",
                  "--device", device])
        err = capsys.readouterr().err
        assert rc == 2 and f"--device {device}:" in err, err
        assert "Traceback" not in err
        assert not (tmp_path / "c" / "objects").exists() or not any((tmp_path / "c" / "objects").iterdir()), \
            "work ran before the device was checked"
    os.environ.pop("VOLCAP_CL_DEVICE", None)


def test_very_long_path_parameter_is_a_message(tmp_path, capsys):
    p = tmp_path / "g.yaml"
    p.write_text("nodes:\n  r:\n    type: t.readfile\n    params: {path: " + "x" * 5000 + "}\n")
    found = problems_of(p)
    assert any(x.startswith(f"{p}:4: node 'r': parameter 'path'") and "too long" in x for x in found), found
    assert cli(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Errno" not in err and len(err) < 1000, err


def test_output_path_must_stay_in_the_output_folder(tmp_path):
    p = tmp_path / "g.yaml"
    for bad, needle in (("/etc/passwd_{frame}", "relative"), ("../up_{frame}.txt", "inside"),
                        ("y" * 300 + "_{frame}.txt", "too long")):
        p.write_text(f"nodes:\n  a: {{type: t.source}}\n  w:\n    type: t.write\n    in: {{x: a.out}}\n    params: {{path: '{bad}'}}\n")
        found = problems_of(p)
        assert any(x.startswith(f"{p}:6: node 'w': parameter 'path'") and needle in x for x in found), (bad, found)


@pytest.mark.slow
def test_frames_list_is_capped_and_huge_files_are_refused_fast(tmp_path):
    p = tmp_path / "g.yaml"
    p.write_text("frames: [" + ", ".join(str(i) for i in range(3_000_000)) + "]\n" + OK_GRAPH)
    t0 = time.monotonic()
    found = problems_of(p)
    assert time.monotonic() - t0 < 5
    assert any(x.startswith(f"{p}:") and "too large" in x for x in found), found
    from nodegraph import graphfile

    with pytest.raises(ValueError, match="at most"):
        graphfile.parse_frames(list(range(graphfile.MAX_FRAMES + 1)), "here")


def test_node_name_with_trailing_newline_is_refused(tmp_path):
    p = tmp_path / "g.yaml"
    p.write_text('nodes:\n  "m2\\n": {type: t.source}\n  b: {type: t.scale, in: {x: a.out}}\n  a: {type: t.source}\n')
    found = problems_of(p)
    assert any(x.startswith(f"{p}:2:") and "node name" in x for x in found), found


def test_huge_values_are_not_echoed_whole(tmp_path, capsys):
    p = tmp_path / "g.yaml"
    p.write_text("nodes:\n  a: {type: t.source, params: {value: '" + "z" * 100_000 + "'}}\n")
    assert cli(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "expects a number" in err and len(err) < 2000, len(err)


# ---------------------------------------------------------------- found by the fuzz run (tests/fuzz/run_fuzz.py)
def test_a_number_too_long_to_convert_is_a_message(tmp_path, capsys):
    """Python refuses int() of more than 4300 digits: a ValueError traceback from the YAML constructor."""
    p = tmp_path / "g.yaml"
    p.write_text(OK_GRAPH)
    assert cli(["validate", str(p), "--set", "a.value=" + "9" * 5000]) == 2
    p.write_text("nodes:\n  a: {type: t.source, params: {value: " + "9" * 5000 + "}}\n")
    assert cli(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "5,000 digits" in err and "Traceback" not in err, err[:500]


def test_input_folders_that_cannot_be_data_are_refused(tmp_path, capsys):
    """path: / walked the whole file system (with the cache in it) and hung; '' named the graph's own folder."""
    p = tmp_path / "g.yaml"
    for path, needle in (("/", "contains the cache folder"), ("''", "must not be empty"), ("/proc/self", "system folder")):
        p.write_text(f"nodes:\n  d: {{type: t.readdir, params: {{path: {path}}}}}\n")
        t0 = time.monotonic()
        rc = cli(["--cache", str(tmp_path / "cache"), "run", str(p), "--out", str(tmp_path / "o"), "-q", "-j", "1"])
        err = capsys.readouterr().err
        assert rc == 2 and needle in err and time.monotonic() - t0 < 10, (path, rc, err)
