"""`models fetch` pieces that need no network: checksummed atomic downloads, the TArgs fix, renaming, records."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.pose import fetch
from service.pose.fetch import FetchError, add_targs, finish_model, reference_output
from service.pose.model_files import (
    DETECTOR,
    LIGHTNING,
    LOCAL_CONVERSION_SUFFIX,
    ModelFilesError,
    resolve_models,
    sha256_of,
)


def test_download_verifies_and_renames_atomically(tmp_path: Path) -> None:
    source = tmp_path / "upstream.bin"
    source.write_bytes(b"model bytes")
    good = hashlib.sha256(b"model bytes").hexdigest()
    target = tmp_path / "out" / "model.onnx"
    fetch._download(source.as_uri(), target, good, lambda _m: None)
    assert target.read_bytes() == b"model bytes"
    assert oct(target.stat().st_mode & 0o777) == "0o644"

    other = tmp_path / "out" / "other.onnx"
    with pytest.raises(FetchError, match="does not match the pinned"):
        fetch._download(source.as_uri(), other, "0" * 64, lambda _m: None)
    assert not other.exists()
    assert [p.name for p in other.parent.iterdir()] == ["model.onnx"]  # no partial file left behind


def test_download_reuses_a_verified_file(tmp_path: Path) -> None:
    target = tmp_path / "model.onnx"
    target.write_bytes(b"cached")
    messages: list[str] = []
    fetch._download("file:///nonexistent", target, hashlib.sha256(b"cached").hexdigest(), messages.append)
    assert "already present" in messages[0]


def test_add_targs_adds_one_float_per_extra_argument() -> None:
    model = {
        "modelTopology": {
            "node": [
                {"name": "a", "op": "_FusedConv2D", "attr": {"num_args": {"i": "2"}}},
                {"name": "b", "op": "Conv2D", "attr": {}},
                {"name": "c", "op": "_FusedConv2D", "attr": {"num_args": {"i": "1"}, "TArgs": {"list": {}}}},
            ]
        }
    }
    nodes = add_targs(model)["modelTopology"]["node"]
    assert nodes[0]["attr"]["TArgs"] == {"list": {"type": ["DT_FLOAT", "DT_FLOAT"]}}
    assert "TArgs" not in nodes[1]["attr"]
    assert nodes[2]["attr"]["TArgs"] == {"list": {}}  # present already: left alone


def test_finish_model_renames_io_and_records_provenance(tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    helper = onnx.helper
    graph = helper.make_graph(
        [helper.make_node("Identity", ["serving_default_input:0"], ["StatefulPartitionedCall:0"])],
        "g",
        [helper.make_tensor_value_info("serving_default_input:0", onnx.TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info("StatefulPartitionedCall:0", onnx.TensorProto.FLOAT, [1, 2])],
    )
    path = tmp_path / "m.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)]), str(path))
    model = onnx.load_from_string(finish_model(path, fetch.TFJS_SOURCES[1]))
    assert [i.name for i in model.graph.input] == ["input"] and [o.name for o in model.graph.output] == ["output_0"]
    assert list(model.graph.node[0].input) == ["input"] and list(model.graph.node[0].output) == ["output_0"]
    meta = {p.key: p.value for p in model.metadata_props}
    assert "Lightning" in meta["source"] and meta["license"].startswith("Apache-2.0")


@pytest.mark.parametrize("key", ["thunder", "lightning"])
def test_reference_matches_the_pinned_files(model_dir: Path, key: str) -> None:
    """REFERENCE was recorded from the pinned files; a wrong table would reject every good conversion."""
    spec = {"thunder": fetch.THUNDER, "lightning": LIGHTNING}[key]
    got = reference_output(model_dir / spec.file_name, fetch.POSE_INPUT_PX[key])
    np.testing.assert_allclose(got, fetch.REFERENCE[key], atol=1e-4)
    source = next(s for s in fetch.TFJS_SOURCES if s.spec.key == key)
    assert fetch.verify_converted(model_dir / spec.file_name, source) == "sha256"


def test_locally_converted_file_is_accepted_only_with_its_record(model_dir: Path, tmp_path: Path) -> None:
    shutil.copyfile(model_dir / DETECTOR.file_name, tmp_path / DETECTOR.file_name)
    path = tmp_path / LIGHTNING.file_name
    data = bytearray((model_dir / LIGHTNING.file_name).read_bytes())
    data.extend(b"\0" * 16)  # stands in for a re-conversion: other bytes, other size
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFilesError):
        resolve_models(tmp_path, "lightning")
    record = path.with_name(path.name + LOCAL_CONVERSION_SUFFIX)
    record.write_text(json.dumps({"sha256": sha256_of(path), "replaces_sha256": LIGHTNING.sha256}))
    assert resolve_models(tmp_path, "lightning").pose == path
    record.write_text(json.dumps({"sha256": "0" * 64, "replaces_sha256": LIGHTNING.sha256}))
    with pytest.raises(ModelFilesError):
        resolve_models(tmp_path, "lightning")
