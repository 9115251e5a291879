"""Run CoACD in a child process: ``python -m spread.assets.coacd_worker`` reads an ``.npz`` (vertices,
faces, settings as JSON) on stdin and writes the hulls' ``.npz`` (vertices, counts) on stdout.

CoACD can abort the whole process on some inputs (an uncaught C++ ``std::logic_error``, "unexpected code
path was hit"), which would take an import worker down with it; in a child process it is one failed
decomposition (:func:`spread.assets.decompose.convex_decomposition` then falls back, and says so).
"""

from __future__ import annotations

import io
import json
import sys

import numpy as np


def main() -> None:
    import coacd

    data = np.load(io.BytesIO(sys.stdin.buffer.read()), allow_pickle=False)
    settings = json.loads(str(data["settings"]))
    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(data["vertices"], np.float64), np.asarray(data["faces"], np.int64)),
                            **settings)
    verts = [np.asarray(v, np.float64).reshape(-1, 3) for v, _ in parts]
    out = io.BytesIO()
    np.savez(out, vertices=np.concatenate(verts) if verts else np.zeros((0, 3)),
             counts=np.array([len(v) for v in verts], np.int64))
    sys.stdout.buffer.write(out.getvalue())


if __name__ == "__main__":
    main()
