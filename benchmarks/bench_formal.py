"""The hand-offs' unbounded proofs (tests/test_filtered_formal.py; the harnesses: blockray.synth.handoff_harness): the FIFOs' memories kept as
SMT arrays against mapped to flip-flops (``prove(..., script=("memory_map", "opt -fast"))``),
side by side in one run.

    nice python benchmarks/bench_formal.py

For the 1 x 1 hand-off (``InOrderResolve``, induction depth 20) and the array's
(``ArrayResolve``, depth 12), each way: sby's verdict, the wall time and sby's process time
(its own and its solvers' CPU), and the ratio of the two ways. Both must PASS.
"""

import re

from _run_header import print_run_header

import blockray.synth.handoff_harness as f
from blockray.synth.formal import prove

PROOFS = {
    "InOrderResolve": (lambda: f.HandoffHarness(f.PROOF_DEPTH, f.PROOF_TAG_BITS, latency=f.PROOF_LATENCY,
                                                invariants=True, max_stall=f.MAX_STALL), f.INDUCTION_DEPTH),
    "ArrayResolve": (lambda: f.ArrayHandoffHarness(**f.ARRAY_PROOF, invariants=True), f.ARRAY_INDUCTION_DEPTH),
}
WAYS = {"smt-arrays": (), "flip-flops": f.MEMORIES_AS_FLOPS}


def main():
    print_run_header()
    print(f"{'proof':15s} {'memories':11s} {'status':6s} {'wall s':>7s} {'cpu s':>6s} {'wall ratio':>10s}")
    for name, (harness, depth) in PROOFS.items():
        walls = []
        for way, script in WAYS.items():
            result = prove(harness(), name="p", mode="prove", depth=depth, script=script, timeout=1800)
            cpu = re.search(r"Elapsed process time \[H:MM:SS \(secs\)\]: \S+ \((\d+)\)", result.log)
            walls.append(result.seconds)
            ratio = f"{walls[0] / walls[1]:.2f}" if len(walls) == 2 else ""
            print(f"{name:15s} {way:11s} {result.status:6s} {result.seconds:7.1f} {cpu.group(1) if cpu else '?':>6s} "
                  f"{ratio:>10s}", flush=True)
            assert result.passed, result.log[-2000:]


if __name__ == "__main__":
    main()
