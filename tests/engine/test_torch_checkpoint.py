"""Our torch-free checkpoint reader: the real XFeat weights by name and shape, and hostile pickles refused."""

import io
import os
import pickle
import zipfile

import numpy as np
import pytest

from app.engine.convert.torch_checkpoint import UnsafeCheckpoint, read_state_dict
from app.engine.convert.xfeat_onnx import read_wheel, verify_wheel
from app.engine.errors import ModelBuildError


def test_xfeat_tensors_have_the_documented_names_and_shapes(xfeat_wheel):
    weights, _ = read_wheel(xfeat_wheel)
    sd = read_state_dict(weights)
    assert len(sd) == 122
    assert sd["skip1.1.weight"].shape == (24, 1, 1, 1) and sd["skip1.1.bias"].shape == (24,)
    assert sd["block1.0.layer.0.weight"].shape == (4, 1, 3, 3)
    assert sd["block5.3.layer.0.weight"].shape == (64, 128, 1, 1)
    assert sd["block_fusion.2.weight"].shape == (64, 64, 1, 1)
    assert sd["heatmap_head.2.weight"].shape == (1, 64, 1, 1)
    assert sd["keypoint_head.3.weight"].shape == (65, 64, 1, 1) and sd["keypoint_head.3.bias"].shape == (65,)
    assert sd["block3.1.layer.1.num_batches_tracked"].dtype == np.int64
    assert sd["block3.1.layer.1.num_batches_tracked"].shape == ()
    # Running variances are positive and weights finite: the bytes were read at the right offsets.
    assert all((v > 0).all() for k, v in sd.items() if k.endswith("running_var"))
    assert all(np.isfinite(v).all() for v in sd.values())
    n_backbone = sum(v.size for k, v in sd.items() if not k.startswith("fine_matcher.") and v.dtype == np.float32)
    assert 0.6e6 < n_backbone < 0.7e6  # the paper's 0.66 M parameters


class _RunsCode:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _checkpoint_with(payload: bytes) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("archive/data.pkl", payload)
        zf.writestr("archive/version", "3\n")
    return buf.getvalue()


def test_a_hostile_pickle_is_refused_without_running(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"w": _RunsCode(str(marker))}, protocol=2)
    with pytest.raises(UnsafeCheckpoint, match=r"(posix|os)\.system"):
        read_state_dict(_checkpoint_with(payload))
    assert not marker.exists()
    # The same payload through the standard unpickler does run: the test would notice a permissive reader.
    pickle.loads(payload)
    assert marker.exists()


def test_other_globals_and_non_tensor_contents_are_refused():
    with pytest.raises(UnsafeCheckpoint, match="builtins.eval"):
        read_state_dict(_checkpoint_with(b"cbuiltins\neval\n(S'1'\ntR."))
    with pytest.raises(ModelBuildError, match="plain state dict"):
        read_state_dict(_checkpoint_with(pickle.dumps({"w": [1, 2]}, protocol=2)))
    with pytest.raises(ModelBuildError, match="zip"):
        read_state_dict(b"not a zip")


def test_a_tampered_wheel_is_refused(xfeat_wheel, tmp_path):
    bad = tmp_path / xfeat_wheel.name
    bad.write_bytes(xfeat_wheel.read_bytes() + b"\0")
    with pytest.raises(ModelBuildError, match="sha256"):
        verify_wheel(bad)
