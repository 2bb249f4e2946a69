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

__all__ = ["share_modules"]

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
