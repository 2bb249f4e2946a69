"""cocotb test of the Verilog LeanBench (run by tests/test_lean.py, not by pytest).

BLOCKRAY_STEPS: a pickle of (steps, words, bits, rows, cols, depth) written by the pytest side;
BLOCKRAY_OUT: a JSON file for what the bench saw (the cycle each step was presented, each
marker's cycle and ``hit`` then), which the pytest side compares with the model. The driver is
tests/lean_bench.py's, as in the Amaranth simulator: inputs on the falling edge, outputs read in
the read-only phase before the rising edge.
"""

import json
import os
import pickle

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import ClockCycles, FallingEdge, ReadOnly

from lean_bench import StepDriver


@cocotb.test()
async def lean_steps(dut):
    with open(os.environ["BLOCKRAY_STEPS"], "rb") as f:
        steps, words, bits, rows, cols, depth = pickle.load(f)
    driver = StepDriver(steps, words, bits, rows, cols, depth)
    Clock(dut.clk, 10, unit="ns").start()
    dut.rst.value = 1
    dut.valid.value = 0
    dut.mark.value = 0
    dut.mark_data.value = 0
    await ClockCycles(dut.clk, 2)
    await FallingEdge(dut.clk)
    dut.rst.value = 0
    limit = 60 * len(steps) + 500
    while not driver.done:
        for name, value in driver.inputs().items():
            getattr(dut, name).value = value
        await ReadOnly()
        driver.observe(int(dut.delivered.value), int(dut.mark_out.value), int(dut.hit.value))
        assert driver.t < limit, "the array stopped delivering"
        await FallingEdge(dut.clk)
    with open(os.environ["BLOCKRAY_OUT"], "w") as f:
        json.dump({"presented": driver.presented, "marks": driver.marks, "hits": driver.hits}, f)
