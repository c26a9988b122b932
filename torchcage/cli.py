"""Command line: ``torchcage demo``, ``torchcage deform``, ``torchcage view``, ``torchcage make-cage``,
``torchcage bench``.

``torchcage demo`` runs the main job on data bundled with the package: it embeds a mesh in its
cage, deforms it with a bent and twisted pose of the cage, and writes the meshes, the cages and a
picture. ``torchcage deform`` does the same for your files. ``torchcage view`` serves the cage editor
in the browser (:mod:`torchcage.viewer`). ``torchcage make-cage`` makes an enclosing cage for a mesh
(:func:`torchcage.make_cage`); ``deform`` and ``view`` take ``--cage auto`` for the same.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import torch

from torchcage.cage import Cage
from torchcage.families import family
from torchcage.functional.deform import OUTSIDE_TOLERANCE
from torchcage.methods import METHOD_EXTRAS, METHOD_HELP, METHOD_NAMES, METHODS, OUTSIDE_EFFECT, build_module

__all__ = ["main"]

#: The editor's default port (``torchcage view``); a free one is taken when it is busy.
DEFAULT_PORT = 8765
#: Mesh formats written by ``deform --format`` (OBJ directly, the others through trimesh).
FORMATS = ("obj", "ply", "glb", "stl", "off")
#: Choices of ``--up`` (the mesh's up axis, for pictures and the editor's camera).
UP_CHOICES = ("auto", "x", "y", "z")
#: ``--up auto`` takes z when the mesh's z extent is the largest and at least this many times its
#: y extent (a z-up model standing, like the bundled bar); otherwise y, the OBJ convention.
UP_Z_RATIO = 1.5
UP_HELP = (
    "the mesh's up axis, for the picture: x, y, z, or auto (default): z when the mesh is longest along z and "
    f"at least {UP_Z_RATIO:g} times longer along z than along y (a z-up model standing), else y (the OBJ "
    "convention; the axis of least extent is often not up)"
)


def up_axis(choice: str, vertices: torch.Tensor) -> str:
    """The up axis for ``--up choice``: ``choice`` itself, or for ``"auto"`` the rule of
    :data:`UP_HELP` (z for a mesh longest along z by :data:`UP_Z_RATIO` over y, else y).

    Args:
        choice: ``"auto"``, ``"x"``, ``"y"`` or ``"z"``.
        vertices: ``(N, 3)`` mesh vertices.

    Examples:
        >>> import torch
        >>> standing, lying = torch.tensor([[0.0, 0, 0], [1, 1, 3]]), torch.tensor([[0.0, 0, 0], [3, 1, 1]])
        >>> up_axis("auto", standing), up_axis("auto", lying), up_axis("x", lying)
        ('z', 'y', 'x')
    """
    if choice not in UP_CHOICES:
        raise ValueError(f"up must be one of {', '.join(UP_CHOICES)}, got {choice!r}")
    if choice != "auto":
        return choice
    if vertices.shape[0] == 0 or vertices.shape[-1] != 3:
        return "y"
    extent = (vertices.amax(0) - vertices.amin(0)).double()
    x, y, z = (float(e) for e in extent)
    return "z" if z >= x and z >= UP_Z_RATIO * y else "y"


class _Timer:
    def __init__(self) -> None:
        self.rows: list[tuple[str, float]] = []

    def __call__(self, label: str):
        timer = self

        class _Step:
            def __enter__(self) -> None:
                self.t = time.perf_counter()

            def __exit__(self, *exc: object) -> None:
                timer.rows.append((label, time.perf_counter() - self.t))

        return _Step()

    def report(self) -> str:
        width = max(len(k) for k, _ in self.rows)
        return "\n".join(f"  {k:<{width}}  {t * 1000:9.1f} ms" for k, t in self.rows)


def deform_files(
    cage_path: str | Path,
    deformed_path: str | Path | None,
    mesh_path: str | Path,
    out_dir: str | Path,
    *,
    method: str = "mvc",
    picture: bool = True,
    quiet: bool = False,
    mesh_format: str = "obj",
    up: str = "auto",
    azimuth: float = 35.0,
    elevation: float = 20.0,
    strict: bool = False,
    cage_vertices: int = 200,
    cage_kind: str | None = None,
    tol: float | None = None,
) -> dict[str, Path]:
    """Deform a mesh with a cage and its deformed pose; write the results into ``out_dir``.

    ``cage_path="auto"`` makes the cage from the mesh (:func:`torchcage.make_cage` with
    ``cage_vertices`` and ``cage_kind``: by default quads for ``qmvc`` and ``qgc``, triangles
    otherwise); ``deformed_path=None`` deforms with the rest cage itself (the identity: a start for
    posing ``rest_cage.obj``, e.g. in ``torchcage view``).

    Writes ``rest_mesh.<fmt>``, ``deformed_mesh.<fmt>`` (``mesh_format``: obj, ply, glb, stl, off;
    all but OBJ through trimesh), ``rest_cage.obj``, ``deformed_cage.obj`` (quads kept) and, with
    ``picture=True``, ``deformation.png`` (rest and deformed side by side, seen with ``up`` as the
    vertical axis, ``"auto"`` by :func:`up_axis`, from the camera's ``azimuth`` and ``elevation``
    in degrees).

    Mesh vertices outside the cage (by more than
    :data:`torchcage.functional.deform.OUTSIDE_TOLERANCE` of its size) are reported for every
    method, with their count, how far out they reach and what the method does with them; with
    ``strict`` they are an error. ``tol`` (``qmvc`` and ``qgc``) computes the quad integrals to that relative
    tolerance instead of the papers' Riemann sums.

    Returns:
        The paths written, by name.

    Raises:
        ValueError: an unknown method, format or up axis; ``tol`` with a method other than
            ``qmvc`` and ``qgc``; with ``strict``, points outside the cage.
    """
    method = family(method).short
    if mesh_format not in FORMATS:
        raise ValueError(f"unknown mesh format {mesh_format!r}; choose from {', '.join(FORMATS)}")
    if up not in UP_CHOICES:
        raise ValueError(f"up must be one of {', '.join(UP_CHOICES)}, got {up!r}")
    if tol is not None and not family(method).tol:
        raise ValueError(
            f"--tol is an option of --method qmvc and qgc (the quad integrals to a tolerance), not {method}"
        )
    import torchcage
    from torchcage.functional.deform import find_outside
    from torchcage.viz import Panel, render_panels

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timer = _Timer()
    auto = str(cage_path) == "auto"
    with timer("load"):
        v, f = torchcage.load_mesh(mesh_path)
        loaded = None if auto else torchcage.load_cage(cage_path)
        # a pose may fold through itself
        posed = None if deformed_path is None else torchcage.load_cage(deformed_path, check_intersections=False)
    if loaded is None:
        with timer(f"make cage ({cage_vertices} vertices)"):
            cage = auto_cage(v, f, cage_vertices, _cage_kind(cage_kind, method), quiet)
    else:
        cage = loaded
    pose = cage if posed is None else posed
    if pose.num_vertices != cage.num_vertices or not (
        torch.equal(pose.triangles, cage.triangles) and torch.equal(pose.quads, cage.quads)
    ):
        hint = (
            f"; with --cage auto, pose the made cage {Path(out_dir) / 'rest_cage.obj'} (written by a run without "
            "--deformed, e.g. in torchcage view) and pass that file as --cage"
            if auto
            else ""
        )
        raise torchcage.CageError(
            f"the deformed cage {deformed_path} must have the rest cage's faces and {cage.num_vertices} vertices{hint}"
        )
    with timer("outside check"):
        found = find_outside(v, cage)
    if found.count:
        message = found.message(OUTSIDE_EFFECT[method])
        if strict:
            raise ValueError(f"{message} (--strict)")
        print(f"torchcage: warning: {message}", file=sys.stderr)
    with timer(f"coordinates ({method}, {v.shape[0]} points, {cage.num_vertices} cage vertices)"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            module = build_module(
                method,
                cage,
                v,
                progress=not quiet and (method == "lbc" or v.shape[0] * cage.num_vertices > 5e6),
                tol=tol,
            )
    for w in caught:
        if issubclass(w.category, torchcage.OutsideCageWarning):
            if found.count:
                continue  # said above, for every method alike
            if strict:
                raise ValueError(f"{w.message} (--strict)")
        print(f"torchcage: warning: {w.message}", file=sys.stderr)
    with timer("deform"):
        with torch.no_grad():
            deformed = module(pose.vertices)
    paths = {
        "rest_mesh": out / f"rest_mesh.{mesh_format}",
        "deformed_mesh": out / f"deformed_mesh.{mesh_format}",
        "rest_cage": out / "rest_cage.obj",
        "deformed_cage": out / "deformed_cage.obj",
    }
    with timer("write meshes"):
        torchcage.save_mesh(paths["rest_mesh"], v, f)
        torchcage.save_mesh(paths["deformed_mesh"], deformed, f)
        torchcage.save_cage(paths["rest_cage"], cage)
        torchcage.save_cage(paths["deformed_cage"], cage, pose.vertices)
    if picture:
        with timer("picture"):
            edges = cage.unique_edges()
            # the renderer looks at z-up worlds: turn the chosen up axis into z (a rotation)
            turn = _TURN[up_axis(up, v)]
            from torchcage.viz import CAGE_EDGE_COLOR, MESH_COLOR

            faces_desc = ", ".join(
                f"{n} {kind}"
                for n, kind in ((cage.triangles.shape[0], "triangles"), (cage.quads.shape[0], "quads"))
                if n
            )
            image = render_panels(
                [
                    Panel(v[:, turn], f, cage.vertices[:, turn], edges, title=f"rest: {v.shape[0]:,} mesh vertices"),
                    Panel(
                        deformed[:, turn], f, pose.vertices[:, turn], edges, title=f"deformed: {METHOD_NAMES[method]}"
                    ),
                ],
                size=800,
                azimuth=azimuth,
                elevation=elevation,
                legend=[("mesh", MESH_COLOR), (f"cage ({cage.num_vertices} vertices, {faces_desc})", CAGE_EDGE_COLOR)],
            )
            paths["picture"] = out / "deformation.png"
            image.save(paths["picture"])
    if not quiet:
        print("wrote:")
        for p in paths.values():
            print(f"  {p}")
        print("timings:")
        print(timer.report())
    return paths


#: Axis permutations (rotations) that bring the up axis to z, the renderer's vertical.
_TURN = {"z": [0, 1, 2], "y": [2, 0, 1], "x": [1, 2, 0]}


def _default_kind(method: str) -> Literal["triangle", "quad"]:
    return "quad" if method in ("qmvc", "qgc") else "triangle"


def _cage_kind(kind: str | None, method: str) -> Literal["triangle", "quad"]:
    """``--cage-kind``, or the method's default: quads for ``qmvc`` and ``qgc``, else triangles."""
    if kind is None:
        return _default_kind(method)
    if kind == "triangle":
        return "triangle"
    if kind == "quad":
        return "quad"
    raise ValueError(f"cage kind must be 'triangle' or 'quad', got {kind!r}")


def auto_cage(
    vertices: torch.Tensor, faces: torch.Tensor, target: int, kind: Literal["triangle", "quad"], quiet: bool = False
) -> Cage:
    """A cage made from a mesh for ``--cage auto`` (:func:`torchcage.make_cage`, progress on stderr)."""
    import torchcage

    return torchcage.make_cage(vertices, faces, target_vertices=target, kind=kind, progress=not quiet)


def _make_cage(args: argparse.Namespace) -> int:
    """Make a cage for a mesh; write it (quads kept), a picture, and its measures."""
    import torchcage
    from torchcage.cagegen import measure_cage
    from torchcage.viz import CAGE_EDGE_COLOR, MESH_COLOR, Panel, render_panels

    if not Path(args.mesh).exists():
        raise FileNotFoundError(f"no such file: {args.mesh}")
    out = Path(args.out)
    if out.suffix.lower() != ".obj":
        raise ValueError(f"--out must name an .obj file (the cage), got {args.out}")
    v, f = torchcage.load_mesh(args.mesh)
    start = time.perf_counter()
    margin = None if args.margin is None else args.margin * float((v.amax(0) - v.amin(0)).norm())
    cage = torchcage.make_cage(
        v, f, target_vertices=args.vertices, kind=args.kind, margin=margin, resolution=args.resolution,
        progress=not args.quiet,
    )  # fmt: skip
    seconds = time.perf_counter() - start
    out.parent.mkdir(parents=True, exist_ok=True)
    torchcage.save_cage(out, cage)
    written = [out]
    if not args.no_picture:
        turn = _TURN[up_axis(args.up, v)]
        faces_desc = f"{cage.triangles.shape[0]} triangles, {cage.quads.shape[0]} quads"
        image = render_panels(
            [
                Panel(
                    v[:, turn], f, cage.vertices[:, turn], cage.unique_edges(),
                    title=f"{Path(args.mesh).name}: {v.shape[0]:,} vertices; made cage: {cage.num_vertices}",
                )
            ],
            size=800, azimuth=args.azimuth, elevation=args.elevation,
            legend=[("mesh", MESH_COLOR), (f"cage ({cage.num_vertices} vertices, {faces_desc})", CAGE_EDGE_COLOR)],
        )  # fmt: skip
        picture = out.with_suffix(".png")
        image.save(picture)
        written.append(picture)
    if not args.quiet:
        r = measure_cage(cage, v, f)
        print(f"made a {args.kind} cage in {seconds:.1f} s: {r.vertices} vertices, {r.triangles} triangles, "
              f"{r.quads} quads ({100 * r.quad_fraction:.0f}%), {r.invalid_quads} invalid quads, "
              f"{r.self_intersections} self-intersections")  # fmt: skip
        print(f"  mesh vertices outside: {r.outside}; least clearance {r.min_clearance:.4f} of the diagonal")
        print(f"  distance from the cage to the mesh (fraction of the diagonal): mean {r.mean_distance:.4f}, "
              f"max {r.max_distance:.4f}")  # fmt: skip
        print("wrote:")
        for p in written:
            print(f"  {p}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    import torchcage

    d = torchcage.data
    deform_files(
        d.path("bar_cage.obj"), d.path("bar_cage_deformed.obj"), d.path("bar.obj"), args.out, method=args.method
    )
    return 0


def _deform(args: argparse.Namespace) -> int:
    deform_files(
        args.cage,
        args.deformed,
        args.mesh,
        args.out,
        method=args.method,
        picture=not args.no_picture,
        mesh_format=args.format,
        up=args.up,
        azimuth=args.azimuth,
        elevation=args.elevation,
        strict=args.strict,
        cage_vertices=args.cage_vertices,
        cage_kind=args.cage_kind,
        tol=args.tol,
    )
    return 0


def _view(args: argparse.Namespace) -> int:
    """Serve the cage editor until Ctrl+C (the bundled bar when no files are given)."""
    import warnings

    import torchcage
    from torchcage.viewer import view

    if (args.mesh is None) != (args.cage is None):
        raise ValueError("give both --mesh and --cage, or neither for the bundled bar")
    mesh = args.mesh or torchcage.data.path("bar.obj")
    cage = args.cage or torchcage.data.path("bar_cage.obj")
    for path in (mesh, None if cage == "auto" else cage, args.deformed):
        if path is not None and not Path(path).exists():
            raise FileNotFoundError(f"no such file: {path}")
    if cage == "auto":
        v, f = torchcage.load_mesh(mesh)
        cage = auto_cage(v, f, args.cage_vertices, _cage_kind(args.cage_kind, args.method))
        Path(args.out).mkdir(parents=True, exist_ok=True)
        made = Path(args.out) / "made_cage.obj"
        torchcage.save_cage(made, cage)
        print(f"torchcage view: made a cage of {cage.num_vertices} vertices, written to {made}", flush=True)
        mesh = (v, f)
    elif args.up == "auto":
        mesh = torchcage.load_mesh(mesh)
    up = up_axis(args.up, mesh[0]) if isinstance(mesh, tuple) else args.up
    options = dict(method=args.method, pose=args.deformed, host=args.host, out=args.out, up=up)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            viewer = view(mesh, cage, port=args.port, verbose=args.verbose, **options)
        except OSError as err:
            if args.port != DEFAULT_PORT:
                raise ValueError(str(err)) from None
            viewer = view(mesh, cage, port=0, verbose=args.verbose, **options)  # the default port is taken
    for w in caught:
        print(f"torchcage: warning: {w.message}", file=sys.stderr)
    print(f"torchcage view: {viewer.url}  ({METHOD_NAMES[args.method]}; Ctrl+C to stop)", flush=True)
    if not args.no_browser:
        viewer.open()
    try:
        while True:
            time.sleep(3600)  # the server answers in its own thread
    except KeyboardInterrupt:
        print("torchcage view: stopped", file=sys.stderr)
    finally:
        viewer.close()
    return 0


def _cage_maker_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--cage-vertices", type=_positive_int, default=200, help="with --cage auto: the cage's vertex count"
    )
    parser.add_argument(
        "--cage-kind", choices=("triangle", "quad"), help="with --cage auto: default quad for qmvc/qgc, else triangle"
    )


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def kernel_library() -> str:
    """Which library serves the CPU kernels: the native variant, or torch and why."""
    from torchcage.backends import native as _native

    if _native.available():
        return f"native ({_native.variant()})"
    reason = _native.failure_reason()
    return "torch (native kernels " + (f"unavailable: {reason})" if reason else "turned off or not built)")


def _bench(args: argparse.Namespace) -> int:
    """Time mean value coordinates on this machine: bundled bar cage, random points inside.

    Prints a header at once, then each row as it is measured (the first native call may build the
    kernels)."""
    import torchcage
    from torchcage import functional as F
    from torchcage._timing import best_of
    from torchcage.backends import native as _native

    cage = torchcage.load_cage(torchcage.data.path("bar_cage.obj")).triangulated()
    print(f"mean value coordinates: {args.points:,} points inside the bundled bar cage "
          f"({cage.triangles.shape[0]} triangles), float64, {torch.get_num_threads()} threads, "
          f"best of {args.repeat}", flush=True)  # fmt: skip
    print(f"kernels: {kernel_library()}", flush=True)
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(args.points, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([1.1, 1.1, 3.2]).double()
    backends = (["native"] if _native.available() else []) + ["torch"]
    print(f"{'backend':<8}{'best ms':>10}{'Mpts/s':>9}", flush=True)
    for backend in backends:
        F.mean_value_coordinates(x[:1000], cage, backend=backend)  # warm up (and build the native kernel)
        _, best, _ = best_of(functools.partial(F.mean_value_coordinates, x, cage, backend=backend), args.repeat)
        print(f"{backend:<8}{1000 * best:>10.1f}{args.points / best / 1e6:>9.2f}", flush=True)
    return 0


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings on the command line: one line, ``torchcage: warning: ...`` (no source line)."""
    print(f"torchcage: warning: {message}", file=sys.stderr if file is None else file, flush=True)


def _epilog() -> str:
    by_extra: dict[str, list[str]] = {}
    for method, extra in METHOD_EXTRAS.items():
        by_extra.setdefault(extra, []).append(method)
    needs = "; ".join(f"--method {', '.join(m)} need pip install 'torchcage[{e}]'" for e, m in by_extra.items())
    plain = ", ".join(m for m in METHODS if m not in METHOD_EXTRAS)
    return (
        f"Extras: --method {plain} need only torch; {needs}; make-cage and --cage auto need "
        "pip install 'torchcage[cage]'; mesh formats other than OBJ need pip install 'torchcage[mesh]'."
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchcage`` command."""
    from torchcage import __version__

    parser = argparse.ArgumentParser(
        prog="torchcage", description="Cage coordinates for deformation.", epilog=_epilog()
    )
    parser.add_argument("--version", action="version", version=f"torchcage {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="deform the bundled bar with its cage; write meshes and a picture")
    demo.add_argument("--out", default="torchcage_demo", help="output folder (default: ./torchcage_demo)")
    demo.add_argument("--method", default="mvc", choices=METHODS, help=METHOD_HELP)
    demo.set_defaults(func=_demo)
    dfm = sub.add_parser("deform", help="deform a mesh with a rest cage and a deformed cage")
    dfm.add_argument(
        "--cage", required=True, help="rest cage (.obj, triangles and quads), or 'auto' to make one from the mesh"
    )
    dfm.add_argument("--deformed", help="deformed cage (.obj, same faces); default: the rest cage (no deformation)")
    _cage_maker_arguments(dfm)
    dfm.add_argument("--mesh", required=True, help="mesh to deform (.obj, or any format trimesh reads)")
    dfm.add_argument("--out", required=True, help="output folder")
    dfm.add_argument("--method", default="mvc", choices=METHODS, help=METHOD_HELP)
    dfm.add_argument("--format", default="obj", choices=FORMATS, help="format of the meshes written (default obj)")
    dfm.add_argument("--up", default="auto", choices=UP_CHOICES, help=UP_HELP)
    dfm.add_argument("--azimuth", type=float, default=35.0, help="picture camera azimuth, degrees")
    dfm.add_argument("--elevation", type=float, default=20.0, help="picture camera elevation, degrees")
    dfm.add_argument("--no-picture", action="store_true", help="skip the PNG picture")
    dfm.add_argument(
        "--strict",
        action="store_true",
        help="fail (exit 2) when mesh vertices lie outside the cage (any method; by more than "
        f"{OUTSIDE_TOLERANCE:g} of its size); without it they warn with their count and how far out they reach",
    )
    dfm.add_argument(
        "--tol", type=float, help="qmvc, qgc: the quad integrals to this relative tolerance (e.g. 1e-8) instead of "
        "the papers' Riemann sums",
    )  # fmt: skip
    dfm.set_defaults(func=_deform)
    vw = sub.add_parser("view", help="the cage editor in the browser: pose a cage, see the mesh deform, save OBJ")
    vw.add_argument("--mesh", help="mesh to deform (.obj, or any format trimesh reads); default: the bundled bar")
    vw.add_argument(
        "--cage", help="rest cage (.obj, triangles and quads), or 'auto' to make one; default: the bundled bar's cage"
    )
    vw.add_argument("--deformed", help="a deformed cage to start from (.obj, the rest cage's faces)")
    vw.add_argument("--method", default="mvc", choices=METHODS, help=METHOD_HELP)
    vw.add_argument("--out", default=".", help="folder that Save writes into (default: the current folder)")
    vw.add_argument("--host", default="127.0.0.1", help="address to listen on (default loopback; others warn)")
    vw.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0: any free port)")
    vw.add_argument(
        "--up", default="auto", choices=UP_CHOICES, help=UP_HELP.replace("for the picture", "for the camera")
    )
    vw.add_argument("--no-browser", action="store_true", help="print the address without opening a browser")
    vw.add_argument("--verbose", action="store_true", help="log each request")
    _cage_maker_arguments(vw)
    vw.set_defaults(func=_view)
    mk = sub.add_parser("make-cage", help="make an enclosing cage for a mesh (torchcage[cage]); write it and a picture")
    mk.add_argument("--mesh", required=True, help="the mesh (.obj, or any format trimesh reads); open meshes are fine")
    mk.add_argument("--out", required=True, help="the cage file to write (.obj, quads kept); the picture goes beside")
    mk.add_argument("--vertices", type=_positive_int, default=200, help="the cage's vertex count (default 200)")
    mk.add_argument("--kind", default="triangle", choices=("triangle", "quad"), help="triangles, or quad-dominant")
    mk.add_argument("--margin", type=float, help="least clearance, fraction of the diagonal (default 0.005)")
    mk.add_argument("--resolution", type=_positive_int, default=128, help="envelope voxels along the longest side")
    mk.add_argument("--up", default="auto", choices=UP_CHOICES, help=UP_HELP)
    mk.add_argument("--azimuth", type=float, default=35.0, help="picture camera azimuth, degrees")
    mk.add_argument("--elevation", type=float, default=20.0, help="picture camera elevation, degrees")
    mk.add_argument("--no-picture", action="store_true", help="skip the PNG picture")
    mk.add_argument("--quiet", action="store_true", help="print nothing but errors")
    mk.set_defaults(func=_make_cage)
    bench = sub.add_parser(
        "bench",
        help="time mean value coordinates on this machine (bundled cage); says which kernel library serves",
    )
    bench.add_argument(
        "--points", type=_positive_int, default=100_000, help="random points inside the cage (default 100000)"
    )
    bench.add_argument(
        "--repeat", type=_positive_int, default=3, help="timed runs per backend; the best is shown (default 3)"
    )
    bench.set_defaults(func=_bench)
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning  # (restored on leaving the block)
        try:
            return args.func(args)
        except (ValueError, TypeError, FileNotFoundError, ImportError) as err:
            print(f"torchcage: error: {err}", file=sys.stderr)
            return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
