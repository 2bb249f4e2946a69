"""One Verilog module and one C++ class for identical instances (the array's processors).

Amaranth emits a Verilog module per elaboratable instance: the R x S processors of an array are
R x S modules with the same body under different names (``\\board.board.array.processor_0_0``,
...). Verilator inlines a module instantiated once, so it compiles every copy and streams all of
that code through the instruction cache each clock cycle. :func:`share_modules` keeps the first
of each set of modules whose text is the same but for the module's name and the local register
Yosys's back end names after the module (``\\$auto$verilog_backend.cc:N:dump_module$K``), and
points every instance at it. The kept modules are the ones Amaranth wrote, so the simulated
design is the same, bit for bit and cycle for cycle.

A module that then has several instances is marked for Verilator: ``no_inline_module`` (else it
inlines it anyway, one copy per instance), and its inputs other than clocks ``public``: without
that Verilator reads each instance's input from the signal driving it, so every instance gets
its own copy of the code again; public inputs are copied into the instance, and the code that
reads them is one function shared by all instances. Clocks stay as they are (a copied clock
would update the instance's registers a step after the rest of the design's), and so do the
inputs a module passes on to a submodule (one of them may be the submodule's clock).
"""

import re

__all__ = ["register_reset", "share_modules"]

_NAME = r"(?:\\\S+ |[A-Za-z_][\w$]*)"
#: a module of Yosys's Verilog back end: its attributes, its header and body, up to ``endmodule``
_MODULE = re.compile(rf"^(?:\(\*[^\n]*\*\)\n)*module ({_NAME})(.*?^endmodule\n)", re.M | re.S)
#: the register Yosys names after the module (it keeps an ``always @*`` from being empty)
_DUMP_REG = re.compile(r"\\\$auto\$verilog_backend\.cc:\d+:dump_module\$\d+ ")
#: an instance: the module's name, then the instance's name and its port list or parameters
_INSTANCE = re.compile(rf"^(\s+)({_NAME})(?=\s+(?:{_NAME}|#)\s*\()", re.M)
_HEADER = re.compile(r"\);\n")
_INPUT = re.compile(rf"^(  input (?:\[\d+:\d+\] )?)({_NAME});$", re.M)
#: a signal that clocks logic, or that the module passes to a submodule (which may clock it)
_CLOCK = re.compile(rf"@\((?:posedge|negedge) ({_NAME})|^\s+\.[\w$]+\(({_NAME})\)", re.M)


def share_modules(verilog):
    """``verilog`` (Yosys's output) with the modules of the same text but their names merged
    into the first of them (repeated until none are left: merging submodules can make their
    parents the same), and each module with more than one instance marked for Verilator as
    the module docstring says."""
    while True:
        modules = list(_MODULE.finditer(verilog))
        first, alias = {}, {}
        for module in modules:
            body = _DUMP_REG.sub(r"\\$dump_module ", module.group(2))
            alias[module.group(1)] = first.setdefault(body, module.group(1))
        if all(name == kept for name, kept in alias.items()):
            break
        parts, end = [], 0
        for module in modules:
            parts.append(verilog[end:module.start()])
            if alias[module.group(1)] == module.group(1):
                parts.append(module.group(0))
            end = module.end()
        parts.append(verilog[end:])
        verilog = _INSTANCE.sub(lambda m: m.group(1) + alias.get(m.group(2), m.group(2)), "".join(parts))
    instances = {}
    for m in _INSTANCE.finditer(verilog):
        instances[m.group(2)] = instances.get(m.group(2), 0) + 1
    return _MODULE.sub(lambda m: _mark(m) if instances.get(m.group(1), 0) > 1 else m.group(0), verilog)


def _mark(module):
    """A module's text with the marks that keep it one C++ class for all its instances."""
    text = module.group(0)
    clocks = {name for pair in _CLOCK.findall(text) for name in pair}
    head = _HEADER.search(text, module.start(2) - module.start()).end()
    body = _INPUT.sub(lambda m: m.group(0) if m.group(2) in clocks else f"{m.group(1)}{m.group(2)} /*verilator public*/;",
                      text[head:])
    return text[:head] + "  /* verilator no_inline_module */\n" + body


def register_reset(verilog, top, *, clk="clk", rst="rst", port="rst_d"):
    """``verilog`` with the top module ``top``'s reset input ``rst`` made a register loaded from
    a new input ``port`` at each rising edge of ``clk``: the design inside sees in each cycle the
    value ``port`` had in the cycle before, so a harness that raises ``port`` one cycle early
    resets the design in the same cycles as before. Verilator evaluates the logic that depends on
    a top input (every processor's ``rst``-masked terms) before each ``eval`` of the model, twice
    a clock cycle; what depends on a register it evaluates once, after the edge. Raises
    ValueError if ``top`` has no such reset and clock."""
    module = next((m for m in _MODULE.finditer(verilog) if m.group(1) == top), None)
    text = None if module is None else module.group(0)
    header = None if text is None else re.match(r"[^;]*\);\n", text[text.index("module "):])
    pattern = rf"(?<=[(, ]){rst}(?=[,)])"
    if (header is None or len(re.findall(pattern, header.group(0))) != 1 or f"  input {rst};\n" not in text
            or f"  input {clk};\n" not in text or re.search(rf"(?<![\w$\\.]){port}(?![\w$])", text)):
        raise ValueError(f"module {top} has no reset input {rst!r} and clock {clk!r} to register")
    start = text.index("module ")
    text = (text[:start] + re.sub(pattern, port, header.group(0)) + text[start + header.end():])
    text = text.replace(f"  input {rst};\n", f"  input {port};\n", 1)
    register = f"  reg {rst} = 1'h0;\n  always @(posedge {clk})\n    {rst} <= {port};\n"
    if f"  wire {rst};\n" in text:
        text = text.replace(f"  wire {rst};\n", register, 1)
    else:
        text = text.replace(f"  input {port};\n", f"  input {port};\n" + register, 1)
    return verilog[:module.start()] + text + verilog[module.end():]
