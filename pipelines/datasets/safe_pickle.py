"""Reading pickled formats without running code from the file.

Two formats the project reads are pickles by design: SMPL model files and the ``np.save(dict)`` files of
ZJU-MoCap (``annots.npy``, ``params/{i}.npy``). ``pickle.load`` and ``np.load(allow_pickle=True)`` call any
function a file names, so a crafted file would run code. Here every global a file names must be on an allowlist:
numpy's array, dtype and scalar reconstruction, scipy.sparse matrix classes, the copyreg helpers that rebuild
instances of those classes, sets, and the codec call that protocol 2 uses for bytes; SMPL files may also name
chumpy classes, which become an inert stub keeping the array (``docs/formats.md §3.1``). Anything else is refused
with an error naming the global.
"""

from __future__ import annotations

import io
import pickle
import threading
from pathlib import Path

import numpy as np
import scipy.sparse

#: (module, name) pairs a pickle may name. numpy 1 and 2 spell the core module differently.
ALLOWED_GLOBALS = {
    *(
        (core, name)
        for core in ("numpy.core.multiarray", "numpy._core.multiarray")
        for name in ("_reconstruct", "scalar")
    ),
    *((core, "_frombuffer") for core in ("numpy.core.numeric", "numpy._core.numeric")),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("copy_reg", "_reconstructor"),
    ("copyreg", "_reconstructor"),
    ("copy_reg", "__newobj__"),
    ("copyreg", "__newobj__"),
    *((module, name) for module in ("__builtin__", "builtins") for name in ("object", "set", "frozenset")),
    ("_codecs", "encode"),  # protocol-2 pickles spell bytes as _codecs.encode(text, "latin1")
}
_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix"}


class UnsafePickleError(pickle.UnpicklingError):
    """A pickle names a global outside the allowlist (the message names it)."""


class ChumpyStub:
    """Stands in for chumpy objects while unpickling: keeps the wrapped array ``x``."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self.__dict__.update(state if isinstance(state, dict) else {"x": state})


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only ``ALLOWED_GLOBALS``, scipy.sparse matrices and (``chumpy=True``) chumpy."""

    def __init__(self, file, *, chumpy: bool = False, **kwargs):
        super().__init__(file, **kwargs)
        self.chumpy = chumpy

    def find_class(self, module: str, name: str):
        if self.chumpy and module.split(".")[0] == "chumpy":
            return ChumpyStub
        if module.startswith("scipy.sparse") and name in _SPARSE:
            return getattr(scipy.sparse, name)
        if (module, name) in ALLOWED_GLOBALS:
            return super().find_class(module, name)
        raise UnsafePickleError(f"refuses to load '{module}.{name}' (only numpy and scipy.sparse data are allowed)")


#: numpy reads every ``.npy`` header with ``ast.literal_eval``, and CPython 3.11 builds syntax trees with one
#: recursion counter per interpreter, so two threads parsing at once can fail with "SystemError: AST constructor
#: recursion depth mismatch". Fits decode views in threads (docs/design.md, *Training views on disk*): every ``.npy``
#: the readers open goes through this lock.
NPY_LOCK = threading.Lock()


def load_npy(path: Path) -> np.ndarray:
    """``np.load(path, allow_pickle=False)`` of a plain ``.npy`` array, under ``NPY_LOCK``."""
    with NPY_LOCK:
        return np.load(path, allow_pickle=False)


def load_npy_object(path: Path):
    """``np.load(path, allow_pickle=True)`` for ``.npy`` files, through ``RestrictedUnpickler`` when the array
    holds Python objects (numeric arrays load without pickle), under ``NPY_LOCK``. Returns the array (0-d for a saved
    dict)."""
    with NPY_LOCK, open(path, "rb") as handle:
        version = np.lib.format.read_magic(handle)
        readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in readers:
            raise ValueError(f"unsupported .npy format version {version}")
        shape, _, dtype = readers[version](handle)
        if not dtype.hasobject:
            handle.seek(0)
            return np.load(handle, allow_pickle=False)
        array = RestrictedUnpickler(io.BytesIO(handle.read()), encoding="latin1").load()
    if not isinstance(array, np.ndarray) or array.shape != shape:
        raise UnsafePickleError(f"holds {type(array).__name__}, not the object array its header announces")
    return array
