"""blockray: a special-purpose computer for radiosity (after Narumi, Makino, Ebisuzaki, Omura).

Folders of the design card map to subpackages: ``blockray.host_driver`` (scenes, voxel grid,
block-ray traverse, form factors, solvers), ``blockray.sim`` (the bit-exact board model and the
simulated RTL boards), ``blockray.rtl`` (Amaranth gateware), ``blockray.synth`` (Verilog and
Yosys/nextpnr). Shared definitions live here: :mod:`blockray.params`, :mod:`blockray.records`,
:mod:`blockray.exact`, :mod:`blockray.samples`.
"""

__version__ = "0.1.0"
