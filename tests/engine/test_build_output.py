"""OpenCL compiler output stays out of the user's way: a build that warns prints nothing (neither pyopencl's
CompilerWarning nor the "N warnings generated." PoCL's clang writes to file descriptor 2) unless
VOLCAP_CL_VERBOSE=1, and a build that fails carries the whole build log in its error."""
from __future__ import annotations

import uuid
import warnings

import pytest

from nodegraph import clrt
from nodegraph.errors import VolcapError


def kernel_file(tmp_path, body: str):
    """A kernel that warns (``#warning``) with a unique text, so neither PoCL's cache nor ``program``'s skips the build."""
    tag = f"volcap-test-{uuid.uuid4().hex[:8]}"
    path = tmp_path / f"{tag}.cl"
    path.write_text(f'#warning "{tag}"\n__kernel void k(__global float* a) {{ {body} }}\n')
    return path, tag


def test_a_build_that_warns_prints_nothing_by_default(tmp_path, capfd, monkeypatch):
    monkeypatch.delenv("VOLCAP_CL_VERBOSE", raising=False)
    clrt.context()  # device choice may print on its own; only the build is under test
    capfd.readouterr()
    path, _ = kernel_file(tmp_path, "a[0] = 1.0f;")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clrt.program(path)
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")
    assert not caught, [str(w.message) for w in caught]


def test_verbose_shows_the_build_log(tmp_path, capfd, monkeypatch):
    monkeypatch.setenv("VOLCAP_CL_VERBOSE", "1")
    clrt.context()
    capfd.readouterr()
    path, tag = kernel_file(tmp_path, "a[0] = 1.0f;")
    clrt.program(path)
    _, err = capfd.readouterr()
    assert tag in err and path.name in err


def test_a_failed_build_carries_the_log(tmp_path, capfd, monkeypatch):
    monkeypatch.delenv("VOLCAP_CL_VERBOSE", raising=False)
    clrt.context()
    capfd.readouterr()
    path, tag = kernel_file(tmp_path, "a[0] = undeclared_thing;")
    with pytest.raises(VolcapError, match=f"OpenCL build of {path.name} failed") as info:
        clrt.program(path)
    assert "undeclared_thing" in str(info.value) and tag in str(info.value)  # the error and the warning, from the log
    assert capfd.readouterr() == ("", "")
