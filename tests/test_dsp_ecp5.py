"""The ECP5 netlist of the Intersector (every product a registered MULT18X18D instance) under
cocotb + Verilator, bit- and cycle-exact against blockray.exact like the generic netlist.

``blockray.rtl.processor._product`` has two implementations: fabric registers around ``*``
(generic, tested everywhere else) and, with :class:`blockray.synth.target.ECP5Target`, an
``Instance("MULT18X18D")`` with its input and output registers on. The second is simulated here
with the behavioural model ``synth/ecp5_mult18x18d_sim.v`` (which stops on any configuration
it does not model), through the same cocotb bench as tests/test_processor_cocotb.py: random
input gaps and output backpressure, results compared with the model's expectations in order,
so a latency difference shows up as lost, extra or misplaced results. The Verilator build is
cached by content (``sim.cocotb_support.cached_build``).

The same bench runs the ECP5 netlist with the shooter unit's products on LUT multipliers
(``ECP5Target(fabric_units=...)``, ``blockray synth --fabric-units shooter``) as Yosys builds
them: the Verilog after the ``booth`` pass (``blockray.synth.yosys.booth_verilog``), so the
Booth logic that becomes LUTs is what is simulated; ``@pytest.mark.slow`` also the receiver
unit's (a gate-level netlist five times larger: about 10 minutes of Verilator build).

Default suite: every hard case plus 5 000 random vectors; ``@pytest.mark.slow``: 100 000.
"""

import json
import os
import subprocess
from pathlib import Path

import pytest
from amaranth.back import verilog

from blockray.rtl.processor import MULT18X18D_PARAMS, Intersector
from blockray.sim.cocotb_support import (DEFAULT_BUILD_ARGS, VerilatorBuild, cached_build, run_cocotb,
                                         verilator_env)
from blockray.synth.nextpnr import dsp_estimate
from blockray.synth.target import MULT18X18D_SIM, ECP5Target
from blockray.synth.yosys import booth_verilog

HERE = Path(__file__).parent
BITS = 16
SEED = int(os.environ.get("BLOCKRAY_SEED", "20240605"))
NAME = "intersector_ecp5"

pytestmark = pytest.mark.cocotb


def build_with_model(component, name, *, platform, transform=None):
    """Verilator build of ``component`` converted for ``platform`` (then ``transform(text)``)
    plus the MULT18X18D model."""
    from cocotb_tools.runner import get_runner

    verilator_env()
    text = verilog.convert(component, name=name, emit_src=False, platform=platform)
    if transform is not None:
        text = transform(text)
    files = {f"{name}.v": text, MULT18X18D_SIM.name: MULT18X18D_SIM.read_text()}

    def build(staging, sources):
        get_runner("verilator").build(sources=sources, hdl_toplevel=name, build_dir=staging,
                                      build_args=list(DEFAULT_BUILD_ARGS), waves=False, always=True)

    build_dir, seconds, cached = cached_build(name=name, toplevel=name, files=files,
                                              build_args=DEFAULT_BUILD_ARGS, build=build)
    return VerilatorBuild(name, build_dir, build_dir / f"{name}.v", seconds, cached), text


@pytest.fixture(scope="module")
def ecp5_build():
    build, text = build_with_model(Intersector(BITS), NAME, platform=ECP5Target())
    print(f"verilator build: {'cached' if build.cached else f'{build.seconds:.1f} s'} in {build.build_dir}")
    return build, text


def fabric_build(units):
    name = "intersector_ecp5_" + "_".join(units) + "_luts"
    build, text = build_with_model(Intersector(BITS), name, platform=ECP5Target(units),
                                   transform=lambda text: booth_verilog(text, name))
    print(f"verilator build: {'cached' if build.cached else f'{build.seconds:.1f} s'} in {build.build_dir}")
    return build, text


def run(build, tmp_path, **env):
    stats = tmp_path / "stats.json"
    env = {"BLOCKRAY_BITS": str(BITS), "BLOCKRAY_STATS": str(stats), **{k: str(v) for k, v in env.items()}}
    run_cocotb(build, "cocotb_processor", module_dir=HERE, env=env, test_dir=tmp_path)
    return json.loads(stats.read_text())


def test_the_ecp5_netlist_uses_registered_dsps(ecp5_build):
    """What is simulated is the DSP netlist: 48 MULT18X18D instances at B = 16 (the products'
    DSP count), every one with the parameters the model accepts, and no ``*`` left in it."""
    _, text = ecp5_build
    assert text.count("MULT18X18D #(") == 48
    for key, value in MULT18X18D_PARAMS.items():
        assert text.count(f'.{key}("{value}")') == 48, key
    assert " * " not in text


def check_vectors(build, tmp_path, seed, vectors):
    """Every hard case plus ``vectors`` random ones (``seed``), with input gaps and output
    backpressure: zero mismatches."""
    print(f"seed={seed}")
    stats = run(build, tmp_path, BLOCKRAY_SEED=seed, BLOCKRAY_VECTORS=vectors,
                BLOCKRAY_BUBBLE=0.1, BLOCKRAY_STALL=0.1)
    print(stats)
    assert stats["mismatches"] == 0 and stats["vectors"] >= vectors + stats["hard"]


def test_intersector_ecp5_verilator(ecp5_build, tmp_path):
    check_vectors(ecp5_build[0], tmp_path, SEED, 5_000)


@pytest.mark.slow
def test_intersector_ecp5_verilator_full(ecp5_build, tmp_path):
    check_vectors(ecp5_build[0], tmp_path, SEED + 1, 100_000)


@pytest.mark.parametrize("units", [
    # 150 s of Verilator build and vectors: slow (the all-DSP netlist's vectors run in the default suite)
    pytest.param(("shooter",), marks=pytest.mark.slow),
    # both array-edge units (not FABRIC_UNITS: since 'cell' joined it, that is every product in LUTs)
    pytest.param(("shooter", "receiver"), marks=pytest.mark.slow),
])
def test_intersector_lut_multipliers_verilator(units, tmp_path):
    """Units on Booth LUT multipliers, the rest on DSPs: bit- and cycle-exact like the all-DSP
    netlist."""
    build, text = fabric_build(units)
    # only the DSP pieces are instances (42 with the shooter unit's 6 in LUTs, 18 with both
    # units'); the others are Booth logic, no ``*`` left
    assert text.count("MULT18X18D #(") == dsp_estimate(BITS, fabric_units=units) == 48 - (
        6 if "shooter" in units else 0) - (24 if "receiver" in units else 0)
    assert " * " not in text
    check_vectors(build, tmp_path, SEED, 5_000)


def test_mismatch_fails(ecp5_build, tmp_path):
    """A single wrong expectation makes the run on the ECP5 build fail."""
    with pytest.raises(SystemExit):
        run(ecp5_build[0], tmp_path, BLOCKRAY_SEED=SEED, BLOCKRAY_VECTORS=100,
            BLOCKRAY_FLIP=12345, BLOCKRAY_BUBBLE=0, BLOCKRAY_STALL=0)
    assert json.loads((tmp_path / "stats.json").read_text())["mismatches"] == 1


_PROBE = """
module dsp_probe(input wire clk, output wire [35:0] p);
    MULT18X18D #({params}) dsp (
        {a}, {b}, {c},
        .SIGNEDA(1'b1), .SIGNEDB(1'b1), .SOURCEA(1'b0), .SOURCEB(1'b0),
        .CLK0(clk), .CE0(1'b1), .RST0(1'b0), {p});
    reg [3:0] n = 0;
    always @(posedge clk) begin
        n <= n + 1;
        if (n == 4) begin
            $display("PRODUCT %0d", $signed(p));
            $finish;
        end
    end
endmodule
"""


def _probe(tmp_path, params):
    """Build and run a one-DSP design with ``params`` (A = -3, B = 5) under Verilator --binary."""
    verilator = verilator_env()
    text = _PROBE.format(
        params=", ".join(f'.{k}("{v}")' for k, v in params.items()),
        a=", ".join(f".A{i}(1'b{(-3 >> i) & 1})" for i in range(18)),
        b=", ".join(f".B{i}(1'b{(5 >> i) & 1})" for i in range(18)),
        c=", ".join(f".C{i}(1'b0)" for i in range(18)),
        p=", ".join(f".P{i}(p[{i}])" for i in range(36)))
    tmp_path.mkdir()
    (tmp_path / "probe.v").write_text(text)
    main = tmp_path / "main.cpp"
    main.write_text("""#include "Vdsp_probe.h"
#include "verilated.h"
int main(int argc, char** argv) {
    VerilatedContext ctx; ctx.commandArgs(argc, argv);
    Vdsp_probe top{&ctx};
    for (int i = 0; i < 40 && !ctx.gotFinish(); i++) { top.clk = i & 1; top.eval(); }
    return ctx.gotFinish() ? 0 : 3;
}
""")
    build = subprocess.run([verilator, "--cc", "--exe", "--build", "-Wno-fatal", "-O0", "--top-module", "dsp_probe",
                            "-Mdir", str(tmp_path / "obj"), str(tmp_path / "probe.v"), str(MULT18X18D_SIM), str(main)],
                           capture_output=True, text=True, cwd=tmp_path)
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-2000:]
    return subprocess.run([str(tmp_path / "obj" / "Vdsp_probe")], capture_output=True, text=True)


@pytest.mark.slow
def test_model_computes_and_refuses_other_configurations(tmp_path):
    """The model multiplies signed (-3 x 5 = -15) in the configuration the RTL uses, and stops
    with an error when a register is configured differently (here the output register off)."""
    ok = _probe(tmp_path / "ok", MULT18X18D_PARAMS)
    assert ok.returncode == 0 and "PRODUCT -15" in ok.stdout, ok.stdout + ok.stderr
    bad = _probe(tmp_path / "bad", {**MULT18X18D_PARAMS, "REG_OUTPUT_CLK": "NONE"})
    assert bad.returncode != 0 and "REG_OUTPUT_CLK" in bad.stdout + bad.stderr
