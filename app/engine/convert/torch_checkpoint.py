"""Read a PyTorch checkpoint (a state dict of tensors) without PyTorch, and without running its code.

Why our own reader: the service must not depend on a deep-learning framework, and ``torch.load`` on an
untrusted file unpickles arbitrary globals (a checkpoint can run any code). A checkpoint written by
``torch.save`` since PyTorch 1.6 is a zip holding ``<name>/data.pkl`` (the pickled structure) and one raw
little-endian file per tensor storage, ``<name>/data/<key>``. The pickle only needs a handful of globals
to rebuild a state dict; we unpickle with a whitelist of exactly those and refuse everything else, so a
hostile checkpoint raises ``UnsafeCheckpoint`` instead of executing.
"""

from __future__ import annotations

import collections
import io
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.engine.errors import ModelBuildError


class UnsafeCheckpoint(ModelBuildError):
    """The checkpoint's pickle asks for a global outside the whitelist (it could run code)."""


#: Storage types a state dict may hold, with their numpy dtype (little-endian, as torch writes them).
STORAGE_DTYPES: dict[str, np.dtype] = {
    "FloatStorage": np.dtype("<f4"),
    "DoubleStorage": np.dtype("<f8"),
    "HalfStorage": np.dtype("<f2"),
    "LongStorage": np.dtype("<i8"),
    "IntStorage": np.dtype("<i4"),
    "ShortStorage": np.dtype("<i2"),
    "CharStorage": np.dtype("i1"),
    "ByteStorage": np.dtype("u1"),
    "BoolStorage": np.dtype("?"),
}


@dataclass(frozen=True)
class _StorageType:
    """Stand-in for ``torch.FloatStorage`` etc.: only its dtype matters to us."""

    name: str

    @property
    def dtype(self) -> np.dtype:
        return STORAGE_DTYPES[self.name]


@dataclass(frozen=True)
class _Storage:
    """A storage as the pickle refers to it; its bytes are read from the zip by ``key``."""

    dtype: np.dtype
    data: np.ndarray  # 1-D, the whole storage


def _rebuild_tensor_v2(storage: _Storage, offset, size, stride, requires_grad=False, hooks=None, metadata=None):
    """What ``torch._utils._rebuild_tensor_v2`` does, on numpy: a strided view copied to a fresh array."""
    size = tuple(int(s) for s in size)
    stride = tuple(int(s) for s in stride)
    n = int(np.prod(size)) if size else 1
    if n == 0:
        return np.zeros(size, storage.dtype)
    last = offset + sum((s - 1) * st for s, st in zip(size, stride, strict=True))
    if offset < 0 or last >= len(storage.data):
        raise ModelBuildError(f"tensor of size {size} at offset {offset} overruns its storage")
    item = storage.dtype.itemsize
    view = np.lib.stride_tricks.as_strided(
        storage.data[offset:], shape=size, strides=tuple(st * item for st in stride), writeable=False
    )
    return np.array(view, copy=True)


#: The whole whitelist: (module, name) -> what the unpickler hands back.
_ALLOWED: dict[tuple[str, str], object] = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_v2,
    **{("torch", name): _StorageType(name) for name in STORAGE_DTYPES},
}


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, data: bytes, read_record):
        super().__init__(io.BytesIO(data))
        self._read_record = read_record
        self._storages: dict[str, _Storage] = {}

    def find_class(self, module: str, name: str):
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise UnsafeCheckpoint(
                f"the checkpoint's pickle asks for {module}.{name}, which a state dict of tensors never needs: refused"
            ) from None

    def persistent_load(self, pid):
        # ('storage', storage_type, key, location, numel): the tensor bytes live in data/<key>.
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise UnsafeCheckpoint(f"unexpected persistent id {pid!r}")
        _, stype, key, _location, numel = pid
        if not isinstance(stype, _StorageType) or not isinstance(key, str):
            raise UnsafeCheckpoint(f"unexpected storage reference {pid!r}")
        if key not in self._storages:
            raw = self._read_record(key)
            if len(raw) < numel * stype.dtype.itemsize:
                raise ModelBuildError(f"storage {key} holds {len(raw)} bytes, fewer than {numel} values")
            data = np.frombuffer(raw, dtype=stype.dtype, count=numel)
            self._storages[key] = _Storage(stype.dtype, data)
        return self._storages[key]


def read_state_dict(source: Path | bytes) -> dict[str, np.ndarray]:
    """Tensors of a ``torch.save``-d state dict, by name, as numpy arrays (in file order)."""
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except zipfile.BadZipFile as e:
        raise ModelBuildError("not a PyTorch zip checkpoint (legacy or corrupt file)") from e
    with zf:
        names = zf.namelist()
        pkl = [n for n in names if n.endswith("/data.pkl") and n.count("/") == 1]
        if len(pkl) != 1:
            raise ModelBuildError(f"expected one <name>/data.pkl in the checkpoint, found {pkl}")
        prefix = pkl[0][: -len("data.pkl")]
        byteorder = zf.read(prefix + "byteorder").decode() if prefix + "byteorder" in names else "little"
        if byteorder != "little":
            raise ModelBuildError(f"big-endian checkpoints are not supported ({byteorder})")

        def read_record(key: str) -> bytes:
            name = f"{prefix}data/{key}"
            if name not in names:
                raise ModelBuildError(f"the checkpoint has no storage record {key!r}")
            return zf.read(name)

        obj = _RestrictedUnpickler(zf.read(pkl[0]), read_record).load()
    if not isinstance(obj, dict) or not all(isinstance(v, np.ndarray) for v in obj.values()):
        raise ModelBuildError("the checkpoint is not a plain state dict of tensors")
    return dict(obj)
