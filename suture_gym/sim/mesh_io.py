"""Reading, writing and tetrahedralising meshes from files.

- Tetrahedral meshes are read and written with meshio (any format it knows that carries ``tetra`` cells:
  ``.msh``, ``.vtu``, ``.vtk``, ``.mesh``, ``.xdmf`` ...).
- Closed surface meshes (OBJ / STL / PLY / OFF / GLB ...) are loaded with trimesh and tetrahedralised by one of
  two backends:

  ``"tetwild"``  fTetWild through ``pytetwild`` (optional ``mesh`` extra; MPL-2.0). Good-quality tets that
                 follow the surface; the paper's meshes were made with TetWild. It runs in a child Python
                 process in a scratch directory: fTetWild writes a debug file into the working directory, and
                 the caller's must neither receive it nor change (``os.chdir`` is process-wide).
  ``"voxel"``    built in, no extra dependency: the structured tet grid of :func:`~suture_gym.sim.mesh.box_tet_grid`
                 over the surface's bounding box, keeping the cells whose centre lies inside. The boundary is a
                 staircase at the grid spacing; use it for quick experiments and tests.

  TetGen is deliberately not offered: it bundles AGPL code.

Every mesh returned here has passed :func:`~suture_gym.sim.mesh.validate_tet_mesh`, so a bad file fails at
load time with a ValueError naming the bad element rather than later inside the solver. A file the readers
cannot parse (empty, truncated, garbage) also raises a ValueError naming the file and what went wrong: meshio's
own failure modes (a ``sys.exit(1)`` when no reader accepts the file, bare numpy errors from a truncated one)
never reach the caller. ``.msh`` means Gmsh here, read and written: meshio would write ANSYS and, on a Gmsh file
it failed to parse, try its ANSYS reader, which loops forever on a truncated file. For the same reason (meshio's
PLY reader loops on a truncated header) the surface-only formats are refused by :func:`read_tet_mesh` before
they are opened.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from suture_gym.sim.mesh import MAX_TETS, TetMesh, box_tet_grid, check_tet_budget, signed_volumes

BACKENDS = ("auto", "tetwild", "voxel")

#: Surface-only file formats: they hold no tetrahedra (fill them with :func:`tetrahedralize_surface`).
SURFACE_FORMATS = (".obj", ".off", ".ply", ".stl")

#: File extensions trimesh reads with its own loaders; every other extension goes through meshio.
TRIMESH_FORMATS = (
    ".3dxml", ".3mf", ".ctm", ".dae", ".glb", ".gltf", ".obj", ".off", ".ply", ".step", ".stl", ".stp", ".xaml",
    ".xyz", ".zae",
)


def _require_meshio():
    try:
        import meshio
    except ImportError as exc:  # pragma: no cover - depends on the installed extras
        raise ImportError("reading/writing tet meshes needs meshio: pip install 'suture_gym[mesh]'") from exc
    return meshio


def read_tet_mesh(path: str | Path) -> TetMesh:
    """Read a tetrahedral mesh with meshio.

    Args:
        path: file in any meshio format holding ``tetra`` cells; coordinates are taken to be metres.

    Returns:
        A validated :class:`TetMesh` with every ``tetra`` block concatenated. Vertices that no tet uses are
        dropped (surface-only points some writers add), and tets are re-indexed accordingly.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: naming the file: it is empty, damaged or not a mesh file (what the reader said), a
            surface-only format, a ``.msh`` that is not Gmsh, it has no tetrahedra, or the mesh is invalid
            (inverted/zero-volume tet, non-finite coordinate, open surface...; the message names the element).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"tet mesh file {str(path)!r} does not exist")
    if path.suffix.lower() in SURFACE_FORMATS:
        raise ValueError(
            f"{str(path)!r} is a surface format ({path.suffix}), which holds no tetrahedra: fill it with "
            "tetrahedralize_surface"
        )
    data = _read_meshio(path)
    blocks = [np.asarray(c.data) for c in data.cells if c.type == "tetra"]
    if not blocks:
        kinds = sorted({c.type for c in data.cells})
        raise ValueError(f"{str(path)!r} holds no 'tetra' cells (found {kinds}); a volume mesh is needed")
    tets = np.concatenate(blocks).astype(np.int64)
    vertices = _points(data, path)
    try:
        return _compact(vertices, tets)
    except ValueError as exc:
        raise ValueError(f"{str(path)!r}: {exc}") from exc


def read_tet_regions(path: str | Path, name: str | None = None) -> tuple[TetMesh, np.ndarray]:
    """Read a tetrahedral mesh and an integer tag per tet (material regions: skin, fat, muscle ...).

    Args:
        path: as :func:`read_tet_mesh`.
        name: the cell-data array holding the tags (``"gmsh:physical"`` for Gmsh physical groups,
            ``"medit:ref"`` for Medit references, any name in a ``.vtu``); None: the only integer cell-data array
            of the file, or ``gmsh:physical`` among Gmsh's.

    Returns:
        ``(mesh, tags)``: the mesh as :func:`read_tet_mesh` returns it (tets in the file's order) and ``(T,)
        int64`` tags. Map them to ``0 .. L - 1`` (``np.unique(tags, return_inverse=True)``) for
        :meth:`~suture_gym.sim.model.TissueModel.from_mesh`'s ``tet_material``.

    Raises:
        ValueError: naming the file, as :func:`read_tet_mesh`, or when the tags are missing, not integers, or
            ``name`` is None and the file has several candidate arrays (the message lists them).
    """
    mesh = read_tet_mesh(path)
    path = Path(path)
    data = _read_meshio(path)
    blocks = [k for k, c in enumerate(data.cells) if c.type == "tetra"]
    candidates = sorted(key for key, arrays in data.cell_data.items()
                        if all(np.issubdtype(np.asarray(arrays[k]).dtype, np.integer) for k in blocks))
    if name is None:
        if "gmsh:physical" in candidates:
            name = "gmsh:physical"
        elif len(candidates) == 1:
            name = candidates[0]
        else:
            raise ValueError(f"{str(path)!r}: name the tet tags to read, one of the integer cell data {candidates}"
                             if candidates else f"{str(path)!r} has no integer cell data on its tets to read tags from")
    if name not in data.cell_data:
        raise ValueError(f"{str(path)!r} has no cell data {name!r}; it has {sorted(data.cell_data)}")
    tags = [np.asarray(data.cell_data[name][k]) for k in blocks]
    if not all(np.issubdtype(t.dtype, np.integer) for t in tags):
        raise ValueError(f"{str(path)!r}: cell data {name!r} must hold integer tags, got {tags[0].dtype}")
    return mesh, np.concatenate([t.reshape(-1) for t in tags]).astype(np.int64)


def _read_meshio(path: Path):
    """``meshio.read(path)``, every way a bad file fails turned into a ValueError naming ``path``.

    meshio prints its readers' complaints and calls ``sys.exit(1)`` when none accepts the file; that text is
    captured into the message instead. A ``.msh`` file must be Gmsh (``$MeshFormat`` header): see the module
    docstring.
    """
    meshio = _require_meshio()
    name = repr(str(path))
    with path.open("rb") as fh:
        head = fh.read(64)
    if not head:
        raise ValueError(f"mesh file {name} is empty")
    file_format = None
    if path.suffix.lower() == ".msh":
        if not head.lstrip().startswith(b"$MeshFormat"):
            raise ValueError(
                f"mesh file {name} is not a Gmsh file (no $MeshFormat header); other .msh formats (ANSYS) are "
                "not read: convert it to .vtu or Gmsh"
            )
        file_format = "gmsh"
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            return meshio.read(path, file_format=file_format)
    except (Exception, SystemExit) as exc:
        said = " ".join(printed.getvalue().split()) or "no reader accepted it"
        detail = said if isinstance(exc, SystemExit) else f"{type(exc).__name__}: {exc}"
        raise ValueError(f"mesh file {name} could not be read (damaged or not a mesh file?): {detail}") from exc


def _points(data, path: Path) -> np.ndarray:
    """The ``(N, 3) float64`` points of a meshio mesh read from ``path``; ValueError naming it otherwise."""
    vertices = np.asarray(data.points, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{str(path)!r}: points must be 3-D, got shape {vertices.shape}")
    return vertices


def write_tet_mesh(path: str | Path, mesh: TetMesh, point_data: dict[str, np.ndarray] | None = None,
                   cell_data: dict[str, np.ndarray] | None = None) -> None:
    """Write ``mesh`` (and optional per-vertex arrays, e.g. displacement (N,3) m, and per-tet arrays, e.g.
    integer material tags (T,) for :func:`read_tet_regions`) with meshio.

    The format follows the file extension (``.vtu`` opens in ParaView; ``.msh`` is Gmsh 4.1).
    """
    meshio = _require_meshio()
    point_data = {k: np.asarray(v) for k, v in (point_data or {}).items()}
    for name, values in point_data.items():
        if len(values) != len(mesh.vertices):
            raise ValueError(
                f"point_data[{name!r}] has {len(values)} rows; the mesh has {len(mesh.vertices)} vertices"
            )
    cell_data = {k: np.asarray(v) for k, v in (cell_data or {}).items()}
    for name, values in cell_data.items():
        if len(values) != len(mesh.tets):
            raise ValueError(f"cell_data[{name!r}] has {len(values)} rows; the mesh has {len(mesh.tets)} tets")
    path = Path(path)
    meshio.write(
        path,
        meshio.Mesh(mesh.vertices, [("tetra", np.asarray(mesh.tets, dtype=np.int64))], point_data=point_data,
                    cell_data={k: [v] for k, v in cell_data.items()}),
        file_format="gmsh" if path.suffix.lower() == ".msh" else None,
    )


def load_surface_mesh(source, scale: float = 1.0):
    """Load a closed triangle surface with trimesh and check it can bound a volume.

    Args:
        source: a path (OBJ/STL/PLY/OFF/GLB: anything trimesh reads) or a ``trimesh.Trimesh``.
        scale: factor applied to the coordinates to obtain metres (e.g. 1e-3 for a file in millimetres).

    Returns:
        ``trimesh.Trimesh`` in metres.

    Raises:
        ValueError: an empty, damaged or unreadable file, no triangles, non-finite coordinates, non-positive
            scale, or a surface that is not watertight (open boundary edges or non-manifold edges), naming the
            file.
    """
    import trimesh

    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale!r}")
    name = "mesh" if isinstance(source, trimesh.Trimesh) else repr(str(source))
    if isinstance(source, trimesh.Trimesh):
        surface = source.copy()
    else:
        path = Path(source)
        if not path.exists():
            raise FileNotFoundError(f"surface mesh file {name} does not exist")
        surface = _read_surface_file(path)
    if len(surface.faces) == 0:
        raise ValueError(f"surface {name} has no triangles")
    if not np.all(np.isfinite(surface.vertices)):
        bad = int(np.argwhere(~np.isfinite(surface.vertices))[0, 0])
        raise ValueError(f"surface {name}: vertex {bad} has a non-finite coordinate")
    surface.apply_scale(scale)
    if not surface.is_watertight:
        raise ValueError(
            f"surface {name} is not closed (watertight): it has open or non-manifold edges, so it bounds no "
            "volume; repair it (e.g. trimesh.repair.fill_holes) before tetrahedralising"
        )
    if surface.volume < 0:
        surface.invert()
    return surface


def _read_surface_file(path: Path):
    """Load the triangles of ``path`` as a ``trimesh.Trimesh`` (file units); ValueError naming it if unreadable.

    trimesh's own formats are loaded by trimesh; the rest through :func:`_read_meshio` (trimesh would hand them
    to meshio itself, without the guards against a truncated ``.msh``).
    """
    import trimesh

    name = repr(str(path))
    if path.suffix.lower() not in TRIMESH_FORMATS:
        data = _read_meshio(path)
        blocks = [np.asarray(c.data) for c in data.cells if c.type == "triangle"]
        if not blocks:
            kinds = sorted({c.type for c in data.cells})
            raise ValueError(f"surface mesh file {name} holds no 'triangle' cells (found {kinds})")
        return trimesh.Trimesh(_points(data, path), np.concatenate(blocks), process=True)
    if path.stat().st_size == 0:
        raise ValueError(f"surface mesh file {name} is empty")
    try:
        return trimesh.load(path, force="mesh", process=True)
    except Exception as exc:
        raise ValueError(
            f"surface mesh file {name} could not be read (damaged or not a mesh file?): {type(exc).__name__}: {exc}"
        ) from exc


def tetrahedralize_surface(source, edge_length: float, backend: str = "auto", scale: float = 1.0,
                           max_tets: int = MAX_TETS) -> TetMesh:
    """Fill a closed surface with tetrahedra.

    Args:
        source: path or ``trimesh.Trimesh`` of a closed surface (see :func:`load_surface_mesh`).
        edge_length: target tet edge length in metres (the voxel backend's grid spacing).
        backend: ``"tetwild"``, ``"voxel"``, or ``"auto"`` (tetwild when ``pytetwild`` is installed, else voxel).
        scale: factor converting the file's units to metres.
        max_tets: refuse (ValueError naming ``edge_length`` and ``max_tets``) a fill estimated above this many
            tets, before it starts: the voxel backend builds the grid over the whole bounding box (5 tets per
            cell of ``edge_length``); fTetWild's count is estimated as the volume over a regular tet's.

    Returns:
        A validated :class:`TetMesh` with positively oriented tets.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not (np.isfinite(edge_length) and edge_length > 0):
        raise ValueError(f"edge_length must be a positive finite length in metres, got {edge_length!r}")
    surface = load_surface_mesh(source, scale=scale)
    if backend == "auto":
        backend = "tetwild" if _tetwild_installed() else "voxel"
    lo, hi = surface.bounds
    if backend == "voxel":
        tets = 5 * math.prod(max(1, math.ceil(float(e) / edge_length)) for e in hi - lo)
    else:
        tets = math.ceil(float(surface.volume) / (edge_length**3 / (6.0 * math.sqrt(2.0))))
    extent = " x ".join(f"{float(e):.3g}" for e in hi - lo)
    check_tet_budget(tets, f"edge_length = {edge_length:g} m over a {extent} m surface ({backend} backend)",
                     max_tets, "max_tets")
    if backend == "tetwild":
        if not _tetwild_installed():
            raise ImportError("backend 'tetwild' needs pytetwild: pip install 'suture_gym[mesh]'")
        vertices, tets = _run_tetwild(np.asarray(surface.vertices, dtype=np.float64),
                                      np.asarray(surface.faces, dtype=np.int32), float(edge_length))
        return _compact(vertices, _orient(vertices, tets))
    return voxel_fill(surface, float(edge_length), max_tets)


def _tetwild_installed() -> bool:
    """Whether ``pytetwild`` can be imported (found without importing it: it imports pyvista and VTK)."""
    return importlib.util.find_spec("pytetwild") is not None


#: The child process of :func:`_run_tetwild`: reads ``surface.npz`` and writes ``tets.npz`` in its working directory.
_TETWILD_CHILD = """
import numpy as np
import pytetwild

surface = np.load("surface.npz")
vertices, tets = pytetwild.tetrahedralize(surface["vertices"], surface["faces"],
                                          edge_length_abs=float(surface["edge_length"]), num_threads=1)
np.savez("tets.npz", vertices=np.asarray(vertices, dtype=np.float64), tets=np.asarray(tets, dtype=np.int64))
"""


def _run_tetwild(vertices: np.ndarray, faces: np.ndarray, edge_length: float) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild on the surface ``vertices`` (V, 3) m, ``faces`` (F, 3), in a child process whose working directory
    is a scratch directory (fTetWild writes ``__tracked_surface.stl`` there); returns ``(vertices (N, 3) m,
    tets (T, 4))``. RuntimeError with the child's error output if it fails."""
    with tempfile.TemporaryDirectory(prefix="suture_gym_tetwild_") as scratch:
        np.savez(Path(scratch) / "surface.npz", vertices=vertices, faces=faces, edge_length=edge_length)
        done = subprocess.run([sys.executable, "-c", _TETWILD_CHILD], cwd=scratch, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"fTetWild failed (exit status {done.returncode}): {done.stderr.strip()[-2000:]}")
        with np.load(Path(scratch) / "tets.npz") as result:
            return result["vertices"], result["tets"]


def voxel_fill(surface, spacing: float, max_tets: int = MAX_TETS) -> TetMesh:
    """The voxel backend: the cells of a five-tet grid of ``spacing`` (m) over ``surface.bounds`` whose centres
    lie inside (``surface.contains``); ``surface`` is a ``trimesh.Trimesh`` or any shape with those two (e.g. one
    given by a signed distance, :func:`~suture_gym.sim.anatomy.hand`)."""
    lo, hi = surface.bounds
    cells = np.maximum(np.ceil((hi - lo) / spacing).astype(int), 1)
    size = cells * spacing
    origin = lo - 0.5 * (size - (hi - lo))
    grid = box_tet_grid(size=tuple(size), cells=tuple(int(c) for c in cells), origin=tuple(origin), max_tets=max_tets)
    cell_of_tet = np.floor((grid.vertices[grid.tets].mean(axis=1) - origin) / spacing).astype(np.int64)
    cell_of_tet = np.clip(cell_of_tet, 0, cells - 1)
    flat = np.ravel_multi_index(cell_of_tet.T, tuple(cells))
    unique_cells = np.unique(flat)
    centres = origin + (np.stack(np.unravel_index(unique_cells, tuple(cells)), axis=1) + 0.5) * spacing
    inside_cells = unique_cells[surface.contains(centres)]
    if len(inside_cells) == 0:
        raise ValueError(
            f"edge_length {spacing} m is too coarse: no grid cell centre lies inside the surface "
            f"(extent {np.round(hi - lo, 6).tolist()} m)"
        )
    occupied = np.zeros(tuple(cells), dtype=bool)
    occupied.flat[inside_cells] = True
    occupied = _manifold_cells(occupied)
    keep = occupied.ravel()[flat]
    return _compact(grid.vertices, grid.tets[keep])


def _octant_repairs() -> np.ndarray:
    """``(256,) int64``: for each pattern of occupied cells around a grid vertex (bit ``i + 2 j + 4 k`` for the
    octant ``(i, j, k)``), the octants to fill so that the boundary is a manifold there (0 where it is one: the
    occupied octants, and the empty ones, each form one face-connected group or none). The fill bridges: the
    empty octants with two or more occupied face neighbours, or, where none has, every empty octant."""

    def connected(members: list[int]) -> bool:
        if not members:
            return True
        seen, stack = {members[0]}, [members[0]]
        while stack:
            o = stack.pop()
            for n in (o ^ 1, o ^ 2, o ^ 4):  # face neighbours differ in one coordinate
                if n in members and n not in seen:
                    seen.add(n)
                    stack.append(n)
        return len(seen) == len(members)

    table = np.zeros(256, dtype=np.int64)
    for pattern in range(256):
        full = [o for o in range(8) if (pattern >> o) & 1]
        empty = [o for o in range(8) if not (pattern >> o) & 1]
        if connected(full) and connected(empty):
            continue
        bridges = [o for o in empty if sum((pattern >> n) & 1 for n in (o ^ 1, o ^ 2, o ^ 4)) >= 2]
        table[pattern] = sum(1 << o for o in (bridges or empty))
    return table


_OCTANT_REPAIRS = _octant_repairs()


def _manifold_cells(occupied: np.ndarray) -> np.ndarray:
    """The occupied cells with the cells added that make their boundary a manifold at every grid vertex
    (:func:`_octant_repairs`: cells touching only along an edge or at a corner get bridged), until none is left.
    A centre test on a grid leaves such touches wherever the surface passes close to a cell corner; without this
    the mesh was invalid (non-manifold boundary) at about one cell size in five on the hand of
    :mod:`suture_gym.sim.anatomy`."""
    occupied = occupied.copy()
    while True:
        padded = np.pad(occupied, 1)
        shape = tuple(np.array(padded.shape) - 1)
        code = np.zeros(shape, dtype=np.int64)
        for o in range(8):  # the vertex (a, b, c) of the padded grid has the cells (a + i, b + j, c + k) around it
            i, j, k = o & 1, (o >> 1) & 1, (o >> 2) & 1
            code |= padded[i:i + shape[0], j:j + shape[1], k:k + shape[2]].astype(np.int64) << o
        fill = _OCTANT_REPAIRS[code]
        if not fill.any():
            return occupied
        for o in range(8):
            i, j, k = o & 1, (o >> 1) & 1, (o >> 2) & 1
            padded[i:i + shape[0], j:j + shape[1], k:k + shape[2]] |= ((fill >> o) & 1).astype(bool)
        occupied = padded[1:-1, 1:-1, 1:-1]


def _orient(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap two indices of every negatively oriented tet so that all have positive volume."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    flip = signed_volumes(np.asarray(vertices, dtype=np.float64), tets) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return tets


def _compact(vertices: np.ndarray, tets: np.ndarray) -> TetMesh:
    """Drop unreferenced vertices, re-index; :class:`TetMesh` validates on construction."""
    tets = np.asarray(tets, dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (T, 4), got {tets.shape}")
    if tets.size and (tets.min() < 0 or tets.max() >= len(vertices)):
        bad = int(np.argwhere((tets < 0) | (tets >= len(vertices)))[0, 0])
        raise ValueError(f"tet {bad} references a vertex outside 0..{len(vertices) - 1}: {tets[bad].tolist()}")
    used, inverse = np.unique(tets, return_inverse=True)
    return TetMesh(vertices=vertices[used], tets=inverse.reshape(tets.shape).astype(np.int32))
