"""Output writers: Parquet tables (pyarrow) and VTK ``.vtu`` particle files."""

from __future__ import annotations

import base64
from pathlib import Path

import numpy as np
import pandas as pd


def write_parquet(df: pd.DataFrame, path: str | Path) -> Path:
    """Write a DataFrame as Parquet (pyarrow, zstd-compressed); return the path."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), path, compression="zstd")
    return path


def _b64(arr: np.ndarray) -> str:
    raw = np.ascontiguousarray(arr).tobytes()
    header = np.array([len(raw)], dtype=np.uint32).tobytes()
    return base64.b64encode(header).decode() + base64.b64encode(raw).decode()


def write_vtu(path: str | Path, positions_m: np.ndarray, point_data: dict[str, np.ndarray]) -> Path:
    """Write particles as VTK XML UnstructuredGrid of vertices (binary base64).

    Parameters
    ----------
    path : str or Path
        Output file (``.vtu``).
    positions_m : (n, 3) array
        Particle centres (m).
    point_data : dict of arrays
        Scalars ``(n,)`` or vectors ``(n, 3)``; shown in ParaView (use the
        ``radius_m`` array with a Glyph filter, scale mode scalar, factor 2).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = int(positions_m.shape[0])
    pts = np.asarray(positions_m, dtype=np.float64).reshape(n, 3)
    conn = np.arange(n, dtype=np.int64)
    offs = np.arange(1, n + 1, dtype=np.int64)
    types = np.ones(n, dtype=np.uint8)  # VTK_VERTEX
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" '
        'header_type="UInt32">',
        "<UnstructuredGrid>",
        f'<Piece NumberOfPoints="{n}" NumberOfCells="{n}">',
        "<PointData>",
    ]
    for name, arr in point_data.items():
        a = np.asarray(arr)
        ncomp = 1 if a.ndim == 1 else a.shape[1]
        if np.issubdtype(a.dtype, np.integer):
            a = a.astype(np.int64)
            typ = "Int64"
        else:
            a = a.astype(np.float64)
            typ = "Float64"
        lines.append(f'<DataArray type="{typ}" Name="{name}" NumberOfComponents="{ncomp}" '
                     f'format="binary">{_b64(a)}</DataArray>')
    lines += [
        "</PointData>",
        "<Points>",
        f'<DataArray type="Float64" NumberOfComponents="3" format="binary">{_b64(pts)}'
        "</DataArray>",
        "</Points>",
        "<Cells>",
        f'<DataArray type="Int64" Name="connectivity" format="binary">{_b64(conn)}</DataArray>',
        f'<DataArray type="Int64" Name="offsets" format="binary">{_b64(offs)}</DataArray>',
        f'<DataArray type="UInt8" Name="types" format="binary">{_b64(types)}</DataArray>',
        "</Cells>",
        "</Piece>",
        "</UnstructuredGrid>",
        "</VTKFile>",
    ]
    path.write_text("\n".join(lines))
    return path
