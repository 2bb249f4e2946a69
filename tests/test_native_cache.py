"""The native harness's build cache found by source (sim/native/__init__.py, ``build_native(...,
source=)``): a design built before is found by its parameters and the RTL's source without a
Verilog conversion; another source, a changed RTL source hash, or a build directory that is gone
convert (and build) anew. The Verilator build itself is replaced by a stand-in that makes the
library file, so these run in the default suite; the real build is tests/test_native_board.py's.
"""

import os
import shutil

import pytest
from amaranth.hdl import Module
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

import blockray.sim.native as native


class Echo(wiring.Component):
    """The harness's ports and a register between them."""
    i_bytes: In(stream.Signature(8))
    o_bytes: Out(stream.Signature(8))

    def elaborate(self, platform):
        m = Module()
        m.d.comb += [self.o_bytes.valid.eq(self.i_bytes.valid), self.i_bytes.ready.eq(self.o_bytes.ready)]
        m.d.sync += self.o_bytes.payload.eq(self.i_bytes.payload)
        return m


@pytest.fixture
def converts(tmp_path, monkeypatch):
    """The Verilog conversions build_native runs (a list of designs), with the Verilator build
    replaced by one that writes the library into the directory the content key names."""
    seen = []
    real = native.hdl.convert

    def convert(component, **options):
        seen.append(type(component).__name__)
        return real(component, **options)

    def build(staging, sources):
        (staging / native.LIBRARY).write_text("stand-in")

    def cached_build(**kwargs):
        return real_cached_build(**{**kwargs, "build": build})

    real_cached_build = native.cached_build
    monkeypatch.setattr(native.hdl, "convert", convert)
    monkeypatch.setattr(native, "cached_build", cached_build)
    return seen


def _build(tmp_path, source):
    return native.build_native(Echo, name="echo", cache=tmp_path, source=source)


def test_a_design_built_before_is_found_without_converting_it(tmp_path, converts):
    first = _build(tmp_path, "echo 1")
    assert converts == ["Echo"] and not first.cached
    again = _build(tmp_path, "echo 1")
    assert converts == ["Echo"], "the second build converted the design again"
    assert again.cached and again.build_dir == first.build_dir and again.library.exists()


def test_another_source_or_rtl_converts_anew(tmp_path, converts, monkeypatch):
    first = _build(tmp_path, "echo 1")
    other = _build(tmp_path, "echo 2")
    assert converts == ["Echo", "Echo"]
    # the same Verilog: the content-keyed build is reused, only the conversion ran
    assert other.build_dir == first.build_dir and other.cached
    monkeypatch.setattr(native, "rtl_source_hash", lambda: "an edited rtl/")
    _build(tmp_path, "echo 1")
    assert converts == ["Echo"] * 3


def test_a_build_directory_that_is_gone_is_built_again(tmp_path, converts):
    first = _build(tmp_path, "echo 1")
    shutil.rmtree(first.build_dir)
    again = _build(tmp_path, "echo 1")
    assert converts == ["Echo", "Echo"] and not again.cached and again.library.exists()


def test_the_rtl_source_hash_follows_the_sources(tmp_path, monkeypatch):
    before = native.rtl_source_hash()
    assert native.rtl_source_hash() == before
    monkeypatch.setattr(native, "_version", lambda dist: "another " + dist)
    assert native.rtl_source_hash() != before


def test_several_compiler_flags_reach_make_as_one_variable(tmp_path):
    """``cxxflags`` of more than one flag reach verilated.mk's ``OPT_FAST`` whole: GNU make reads
    the MAKEFLAGS the build sets (a bare space there would start a new make argument)."""
    import subprocess
    (tmp_path / "Makefile").write_text("all:\n\t@echo [$(OPT_FAST)] [$(VK_PCH_I_FAST)]\n")
    flags = ("-O3", "-march=native", "-fno-plt")
    out = subprocess.run(["make", "-s", "-C", str(tmp_path)], env={**os.environ, "MAKEFLAGS": native._makeflags(flags)},
                         capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[-O3 -march=native -fno-plt] []"
