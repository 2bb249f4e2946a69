"""One render configuration: :class:`RenderOptions`, frozen and validated when it is built.

Its groups: :class:`BoardOptions` (which back-end of the registry, host_driver/board/backends.py, and
how it is built), :class:`RayOptions` (the voxel grid, the sample points and how block rays are
formed), :class:`SolveOptions` (the solver and when it stops) and :class:`SetOptions` (host +
board sets on a Dask cluster, the host's cores). The CLI builds one with
:meth:`RenderOptions.from_args`, a library caller with :meth:`RenderOptions.of` from the flat
names (the CLI's option names with ``_`` for ``-``), and :func:`~blockray.host_driver.render.render.render`
takes it as a whole. A bad value raises :class:`~blockray.errors.ParameterError` naming its
parameter (the CLI names the option that set it).

B, the coordinate bits, travels in the board's :class:`~blockray.params.BoardParams`
(``BoardOptions.params.bits``): the B asked for, or None (the default here): the board chooses it
for the scene (a real board: the B its bitstream was built for). The board resolves it once, when
it quantises the scene; from there on the quantised scene and the board's params carry it.
"""

import math
from dataclasses import dataclass, field, fields

from ...cell import Cell
from ...errors import ParameterError, option
from ...params import BoardParams
from ...samples import SampleScheme
from ...link import DEFAULT_BAUD

__all__ = ["BoardOptions", "RayOptions", "SolveOptions", "SetOptions", "RenderOptions", "SOLVERS", "SAMPLE_POINTS",
           "LINK_RAYS",
           "ESTIMATORS", "estimator_of", "cell_option",
           "host_timing"]

SOLVERS = ("progressive", "jacobi", "gauss-seidel", "hierarchical")
SAMPLE_POINTS = ("fixed", "draw", "rows")
#: where a hierarchical link's rays run (host_driver/render/hierarchical.py, "Visibility")
LINK_RAYS = ("spread", "samples", "centroid")

#: ``--estimator``: named sets of the ray options that decide how a pair's visibility is estimated.
#: ``paper``: one fixed sample pattern to the receivers' centroids (the paper; fast, biased at contact
#: lines). ``balanced``: 8 drawn end points per pair on the 1/168 lattice, each row from its own
#: drawn set of shooter samples, for 8x the rays and 3 coordinate bits: nearly no bias left at
#: contact lines; an emitting shooter's pairs get 4x those rows, since its row sum carries the
#: emitted power first-hand (the energy balance it gives, docs/formfactors.md). An option given
#: explicitly wins over its estimator's value.
ESTIMATORS = {
    "paper": {"end_points": "centroid", "end_lattice": 1, "end_draws": 1, "sample_points": "fixed",
              "emitter_factor": 1},
    "balanced": {"end_points": "draw", "end_lattice": 8, "end_draws": 8, "sample_points": "rows",
                 "emitter_factor": 4},
}


def _one_of(name, value, choices):
    if value not in choices:
        raise ParameterError(f"{name} must be one of {', '.join(choices)}, not {value!r}",
                             parameter=name)
    return value


def _integer(value):
    return not isinstance(value, bool) and isinstance(value, int)


@dataclass(frozen=True)
class BoardOptions:
    """The board: ``backend`` (a name of the registry, ``--board``), the machine's ``params``
    (R, S, P and B, None by default: chosen per scene; the memories of a board built per scene
    are fitted to it), ``partition``, the processor ``cell`` (a :class:`~blockray.cell.Cell`),
    a waveform ``vcd``, the simulated host's ``host`` timing ``(idle, backpressure, seed)``,
    link ``faults`` (:class:`~blockray.host_driver.board.framed.LinkFaults`), and for a real board its
    serial ``port`` (one per board) and ``baud``."""
    backend: str = "model"
    params: BoardParams = field(default_factory=lambda: BoardParams(bits=None))
    partition: str = "deal"
    cell: Cell = Cell()
    vcd: object = None
    host: tuple = None
    faults: object = None
    port: tuple = ()
    baud: int = DEFAULT_BAUD

    def __post_init__(self):
        from ..board.backends import backend, check_board       # (the registry imports nothing of this module)
        entry = backend(self.backend)
        if not isinstance(self.params, BoardParams):
            raise ParameterError(f"board params must be BoardParams, not {self.params!r}", parameter="params")
        if self.params.bits is not None:
            if not entry.quantises:
                raise ParameterError(f"bits applies to boards that quantise the scene; the {self.backend} board "
                                     f"is float64", parameter="bits")
        check_board(self)
        if isinstance(self.port, str):
            object.__setattr__(self, "port", tuple(p for p in self.port.split(",") if p))
        if not _integer(self.baud) or self.baud < 1:
            raise ParameterError(f"baud must be a positive integer, not {self.baud!r}", parameter="baud")


@dataclass(frozen=True)
class RayOptions:
    """The voxel grid (``voxels`` per axis; None: the paper's cost model chooses), the shooter
    ``samples`` (a count or a :class:`~blockray.samples.SampleScheme`), the ``traversal`` and
    ``packing`` of block rays (None: the solver's, :attr:`RenderOptions.packing`), where each row
    ends on its receiver (``end_points``, a rule of host_driver/traverse/endpoints.py, with
    ``end_seed`` and ``end_draws`` rows per pair for ``draw``, on a lattice ``end_lattice`` times
    finer than the samples'), where the shooter's samples lie
    (``sample_points``: ``fixed``, one pattern for every patch; ``draw``, stratified and drawn per
    patch from ``sample_seed``; ``rows``, drawn as ``end_draws`` sets stratified together, row d of
    a pair casting from set d; blockray/samples.py), ``emitter_factor`` times the rows for a pair
    whose shooter emits (``draw``), and the fraction of rays whose traversal is measured."""
    voxels: int = None
    samples: SampleScheme = 8
    traversal: str = "block"
    packing: str = None
    end_points: str = "centroid"
    end_seed: int = 0
    end_draws: int = 1
    end_lattice: int = 1
    sample_points: str = "fixed"
    sample_seed: int = 0
    emitter_factor: int = 1
    stats_fraction: float = 0.02

    def __post_init__(self):
        from ..traverse.visibility import PACKINGS, TRAVERSALS
        if self.voxels is not None and (not _integer(self.voxels) or not 1 <= self.voxels <= 256):
            raise ParameterError(f"voxels must be an integer from 1 to 256, not {self.voxels!r}", parameter="voxels")
        count = self.samples
        _one_of("sample_points", self.sample_points, SAMPLE_POINTS)
        if isinstance(self.samples, SampleScheme):       # a scheme's own lattice and draw, unless they contradict
            count, own = self.samples.count, self.samples.end_lattice
            if own != self.end_lattice and 1 not in (own, self.end_lattice):
                raise ParameterError(f"end_lattice {self.end_lattice} contradicts the samples' {own}",
                                     parameter="end_lattice")
            object.__setattr__(self, "end_lattice", max(own, self.end_lattice))
            if self.samples.drawn and self.sample_points == "fixed":
                object.__setattr__(self, "sample_points", "draw" if self.samples.sets == 1 else "rows")
                object.__setattr__(self, "sample_seed", self.samples.seed)
        seed = self.sample_seed if self.sample_points != "fixed" else None
        sets = self.end_draws if self.sample_points == "rows" and _integer(self.end_draws) else 1
        object.__setattr__(self, "samples", SampleScheme(count, self.end_lattice, seed, sets))
        _one_of("traversal", self.traversal, TRAVERSALS)
        if self.packing is not None:
            _one_of("packing", self.packing, PACKINGS)
        from ..traverse.endpoints import ENDS, MAX_DRAWS
        _one_of("end_points", self.end_points, ENDS)
        if self.end_lattice != 1 and self.end_points == "centroid" and self.sample_points == "fixed":
            raise ParameterError(f"end_lattice {self.end_lattice} only moves drawn sample points and end points of the "
                                 "kernel and draw rules; the centroid rule with fixed samples would spend its bits for "
                                 "nothing", parameter="end_lattice")
        if not _integer(self.end_draws) or not 1 <= self.end_draws <= MAX_DRAWS:
            raise ParameterError(f"end_draws must be an integer from 1 to {MAX_DRAWS}, not {self.end_draws!r}",
                                 parameter="end_draws")
        if self.end_draws > 1 and self.end_points != "draw":
            raise ParameterError(f"end_draws {self.end_draws} needs the draw rule: the {self.end_points} rule gives "
                                 "every row of a pair the same point", parameter="end_draws")
        if not _integer(self.emitter_factor) or not 1 <= self.emitter_factor * self.end_draws <= MAX_DRAWS:
            raise ParameterError(f"emitter_factor must be an integer from 1 to {MAX_DRAWS // self.end_draws} (at most "
                                 f"{MAX_DRAWS} rows per pair with end_draws {self.end_draws}), not "
                                 f"{self.emitter_factor!r}", parameter="emitter_factor")
        if self.emitter_factor > 1 and self.end_points != "draw":
            raise ParameterError(f"emitter_factor {self.emitter_factor} needs the draw rule: the {self.end_points} rule "
                                 "gives every row of a pair the same point", parameter="emitter_factor")
        if not _integer(self.sample_seed) or not 0 <= self.sample_seed < 2 ** 63:
            raise ParameterError(f"sample_seed must be an integer from 0 to 2**63 - 1, not {self.sample_seed!r}",
                                 parameter="sample_seed")
        if not _integer(self.end_seed) or not 0 <= self.end_seed < 2 ** 63:
            raise ParameterError(f"end_seed must be an integer from 0 to 2**63 - 1, not {self.end_seed!r}",
                                 parameter="end_seed")
        if not 0 <= self.stats_fraction <= 1:
            raise ParameterError(f"stats_fraction must be from 0 to 1, not {self.stats_fraction!r}",
                                 parameter="stats_fraction")


@dataclass(frozen=True)
class SolveOptions:
    """The ``solver``, its stopping ``tolerance``, ``max_shots`` (progressive) and
    ``max_iterations`` (gathering), the ``closure`` of the visible form factors, and the
    hierarchical solver's refinement threshold ``epsilon`` (a fraction of the emitted power),
    smallest element ``min_area`` (None: 3 levels below each input triangle) and ``link_rays``
    (``spread``: K / 2 rays from half the source's samples to one of the receiver's, a different
    one per link, and K x K where the source emits; ``samples``: K x K rays between the two elements' samples; ``centroid``: K rays from the
    source to the receiver's centroid) and ``clustering`` (initial links between clusters of input
    triangles, host_driver/render/clusters.py), host_driver/render/hierarchical.py."""
    solver: str = "progressive"
    tolerance: float = 1e-3
    max_shots: int = None
    max_iterations: int = 200
    closure: str = "off"
    epsilon: float = 1e-3
    min_area: float = None
    link_rays: str = "spread"
    clustering: bool = True

    def __post_init__(self):
        from ..radiosity.closure import MODES
        _one_of("solver", self.solver, SOLVERS)
        _one_of("link_rays", self.link_rays, LINK_RAYS)
        if not isinstance(self.clustering, bool):
            raise ParameterError(f"clustering must be True or False, not {self.clustering!r}", parameter="clustering")
        if not (isinstance(self.tolerance, (int, float)) and math.isfinite(self.tolerance) and self.tolerance > 0):
            raise ParameterError(f"tolerance must be a positive number, not {self.tolerance!r}",
                                 parameter="tolerance")
        if self.max_shots is not None and (not _integer(self.max_shots) or self.max_shots < 1):
            raise ParameterError(f"max_shots must be at least 1, not {self.max_shots!r}", parameter="max_shots")
        if not _integer(self.max_iterations) or self.max_iterations < 1:
            raise ParameterError(f"max_iterations must be at least 1, not {self.max_iterations!r}",
                                 parameter="max_iterations")
        _one_of("closure", self.closure, MODES)
        for name in ("epsilon", "min_area"):
            value = getattr(self, name)
            if value is None and name == "min_area":
                continue
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ParameterError(f"{name} must be a positive number, not {value!r}", parameter=name)
        if self.solver == "hierarchical" and self.closure == "symmetric":
            raise ParameterError(f"{option('closure')} symmetric averages the two directions of a pair of patches; the "
                                 "hierarchical solver's links have no reverse twins (use off or enforce)", parameter="closure")


@dataclass(frozen=True)
class SetOptions:
    """Where the work runs: ``sets`` host + board sets on a Dask cluster, the user's at
    ``scheduler`` or a local one of ``workers`` processes; ``threads``: cores of the compiled host
    kernels (None: all; the result does not depend on it)."""
    sets: int = 1
    scheduler: str = None
    workers: int = None
    threads: int = None

    def __post_init__(self):
        if not _integer(self.sets) or self.sets < 1:
            raise ParameterError(f"sets must be a positive integer, not {self.sets!r}", parameter="sets")
        for name in ("workers", "threads"):
            value = getattr(self, name)
            if value is not None and (not _integer(value) or value < 1):
                raise ParameterError(f"{name} must be a positive integer, not {value!r}", parameter=name)
        if self.scheduler is not None and self.workers is not None:
            raise ParameterError(f"{option('workers')} sizes the local cluster; a cluster joined with {option('scheduler')} "
                                 "has its own "
                                 "workers", parameter="workers")

    @property
    def distributed(self):
        """The render runs on a Dask cluster."""
        return self.sets != 1 or self.scheduler is not None or self.workers is not None


def cell_option(kind, filter_bits=None):
    """The :class:`~blockray.cell.Cell` of ``--cell KIND`` and ``--filter-bits D[:W[:I]]`` (None: the
    kind's default format; I, lean only: w_k formed from inputs rounded to I bits)."""
    if filter_bits is None:
        return Cell(kind)
    from ...filtered import FilterFormat
    parts = filter_bits.split(":")
    if len(parts) > 3 or not all(p.strip().isdigit() for p in parts):
        raise ParameterError(f"filter_bits must be D, D:W or D:W:I (integers), not {filter_bits!r}",
                             parameter="filter_bits")
    bits = [int(p) for p in parts]
    return Cell(kind, FilterFormat(bits[0], bits[min(1, len(bits) - 1)], bits[2] if len(bits) == 3 else None))


def host_timing(args):
    """The simulated host's link timing from ``--link-idle``, ``--link-backpressure``,
    ``--link-bursts``, ``--link-seed``: ``(idle, backpressure, seed)``, None if it never stalls."""
    from ...sim.drive import HostTiming
    if not (args.link_idle or args.link_backpressure or args.link_bursts):
        return None
    try:
        idle = HostTiming(rate=args.link_idle, burst=args.link_bursts)
        pressure = HostTiming(rate=args.link_backpressure, burst=args.link_bursts)
    except ValueError as e:
        raise ParameterError(f"{option('host')}: {e}", parameter="host") from None
    return idle, pressure, args.link_seed


def _faults(args):
    from ..board.framed import LinkFaults
    return LinkFaults(args.link_faults, args.link_seed)


def estimator_of(ray):
    """The name of the :data:`ESTIMATORS` entry whose options ``ray`` (a :class:`RayOptions`) has, or
    ``"custom"``."""
    return next((name for name, preset in ESTIMATORS.items()
                 if all(getattr(ray, key) == value for key, value in preset.items())), "custom")


def _with_estimator(flat):
    """``flat`` with its ``estimator``'s ray options filled in where they are missing or None."""
    flat = dict(flat)
    name = flat.pop("estimator", None)
    preset = ESTIMATORS[_one_of("estimator", name, tuple(ESTIMATORS))] if name is not None else {}
    if name not in (None, "paper") and flat.get("solver") == "hierarchical":
        raise ParameterError(f"estimator {name}: the hierarchical solver's links choose their rays with "
                             f"{option('link_rays')} and {option('sample_points')} (estimator paper)", parameter="estimator")
    for key in ESTIMATORS["paper"]:
        if flat.get(key) is None:
            flat.pop(key, None)
            if key in preset:
                flat[key] = preset[key]
    return flat


_GROUPS = {"board": BoardOptions, "ray": RayOptions, "solve": SolveOptions, "run": SetOptions}

#: what makes a render distributed (SetOptions.distributed), as an error names it
_DISTRIBUTED = f"{option('sets')}, {option('scheduler')} or {option('workers')}"


@dataclass(frozen=True)
class RenderOptions:
    """Everything a render is configured by, in four groups; see the module docstring."""
    board: BoardOptions = field(default_factory=BoardOptions)
    ray: RayOptions = field(default_factory=RayOptions)
    solve: SolveOptions = field(default_factory=SolveOptions)
    run: SetOptions = field(default_factory=SetOptions)

    def __post_init__(self):
        b, s = self.board, self.solve
        if s.solver == "hierarchical" and self.ray.end_points != "centroid":
            raise ParameterError(f"{option('end_points')}: the hierarchical solver's rays end at its elements' own "
                                 f"points ({option('link_rays')})", parameter="end_points")
        if s.solver == "hierarchical" and self.ray.sample_points == "rows":
            raise ParameterError(f"{option('sample_points')} rows: the hierarchical solver's links have one set of "
                                 "samples per element (fixed or draw)", parameter="sample_points")
        if not self.run.distributed:
            return
        if s.closure != "off" and s.solver != "hierarchical":
            raise ParameterError(f"{option('closure')} needs the whole form-factor matrix on one host; it cannot be used "
                                 f"with {_DISTRIBUTED}", parameter="closure")
        if s.solver == "progressive":
            raise ParameterError(f"{option('sets')}: host + board sets solve by gathering over a matrix; use "
                                 f"{option('solver')} jacobi or gauss-seidel, not {s.solver}", parameter="sets")
        if b.vcd is not None:
            raise ParameterError(f"{option('vcd')} traces one board's simulation; it cannot be used with {_DISTRIBUTED}",
                                 parameter="vcd")
        if b.host is not None:
            raise ParameterError(f"{option('host')} drive one simulated board; they cannot be used with {_DISTRIBUTED}",
                                 parameter="host")
        if b.faults is not None:
            raise ParameterError(f"{option('link_faults')} injects faults on one set's links; it cannot be used with "
                                 f"{_DISTRIBUTED}", parameter="link_faults")
        if b.cell.filtered:
            raise ParameterError(f"{option('cell')} {b.cell.kind} runs one set (not with {_DISTRIBUTED})",
                                 parameter="cell")

    @property
    def packing(self):
        """The block packing in use: ``ray.packing`` if given; else the paper's blocks (the receivers
        whose end points share a voxel) for the uniform solvers, and ``cube`` for the hierarchical
        one, whose links of one source element end in few rows a voxel (1.5x fewer board cycles on
        cornell and the room for about the same host CPU: docs/hierarchical.md, "Packing")."""
        if self.ray.packing is not None:
            return self.ray.packing
        return "cube" if self.solve.solver == "hierarchical" else "voxel"

    @classmethod
    def of(cls, **flat):
        """From the flat names of the groups' fields (``backend``, ``samples``, ``solver``,
        ``sets``, ...); ``rows``, ``cols``, ``boards``, ``bits`` set the board's params;
        ``estimator`` (a name of :data:`ESTIMATORS`) sets the ray options it names that are not
        given (or given as None)."""
        flat = _with_estimator(flat)
        groups = {name: {} for name in _GROUPS}
        owner = {f.name: name for name, group in _GROUPS.items() for f in fields(group)}
        array = {k: flat.pop(k) for k in ("rows", "cols", "boards", "bits") if k in flat}
        for key, value in flat.items():
            if key not in owner:
                raise TypeError(f"RenderOptions.of() got an unknown option {key!r}")
            groups[owner[key]][key] = value
        if array:
            params = groups["board"].get("params") or BoardParams(bits=None)
            groups["board"]["params"] = params.with_(**array)
        if groups["board"].get("params") is None:
            groups["board"].pop("params", None)
        return cls(**{name: _GROUPS[name](**values) for name, values in groups.items()})

    @classmethod
    def from_args(cls, args):
        """From the ``blockray render`` command line (the parsed ``args``: the flat names, and
        ``board``, ``cell``, ``filter_bits``, ``link_*`` as the options give them)."""
        flat = {f.name: getattr(args, f.name) for group in _GROUPS.values() for f in fields(group)
                if hasattr(args, f.name)}
        flat.update(estimator=getattr(args, "estimator", None), backend=args.board, rows=args.rows,
                    cols=args.cols, boards=args.boards, bits=args.bits,
                    cell=cell_option(args.cell, args.filter_bits), host=host_timing(args),
                    faults=None if args.link_faults is None else _faults(args))
        return cls.of(**flat)

    def with_(self, **flat):
        """A copy with the flat options changed."""
        values = {f.name: getattr(getattr(self, group), f.name)
                  for group, cls_ in _GROUPS.items() for f in fields(cls_)}
        values["samples"] = self.ray.samples.count          # its lattice travels as end_lattice
        if flat.get("estimator") is not None:               # the estimator's options, unless given here
            values = {k: v for k, v in values.items() if k not in ESTIMATORS.get(flat["estimator"], {})}
        values.update(flat)
        return RenderOptions.of(**values)
