"""Reading (and, for tests, writing) the weights of a TensorFlow.js graph model without TensorFlow.

A TF.js graph model is ``model.json`` (the graph as a GraphDef in JSON, ``modelTopology.node``, and a
``weightsManifest``) plus binary shards. The manifest lists, per group, the shard files (``paths``,
concatenated in order) and the weights in the order their bytes follow each other: ``name``,
``shape``, ``dtype`` and an optional ``quantization`` (``float16``: 2 bytes a value; ``uint8`` /
``uint16``: ``value * scale + min``). Everything here is the standard library and NumPy.

The reader checks that every group's weights use its shards' bytes exactly (a short or long file is an
error naming it), so a truncated download cannot load.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

_PLAIN = {"float32": np.float32, "int32": np.int32, "bool": np.bool_}
_QUANT = {"float16": np.float16, "uint8": np.uint8, "uint16": np.uint16}


@dataclass
class GraphModel:
    """A TF.js graph model's operations (constants left out) and its weights as float32 / int32 arrays."""

    nodes: list[dict[str, Any]]
    weights: dict[str, np.ndarray]
    quantization: dict[str, str | None]  # weight name -> "float16" / "uint8" / ... or None

    def node(self, name: str) -> dict[str, Any]:
        for n in self.nodes:
            if n["name"] == name:
                return n
        raise KeyError(name)

    def input_size(self) -> int | None:
        """The placeholder's square spatial size (None when it is dynamic, e.g. MultiPose)."""
        for n in self.nodes:
            if n["op"] == "Placeholder":
                dims = [int(d["size"]) for d in n["attr"]["shape"]["shape"]["dim"]]
                return dims[1] if dims[1] > 0 else None
        return None


def fused_ops(node: dict[str, Any]) -> list[str]:
    """The operations fused into a ``_FusedConv2D`` node (e.g. ``["BiasAdd", "Relu6"]``)."""
    return [
        base64.b64decode(s).decode()
        for s in node.get("attr", {}).get("fused_ops", {}).get("list", {}).get("s", [])
    ]


def strides(node: dict[str, Any]) -> int:
    """The spatial stride of a convolution node (NHWC: the second entry)."""
    return int(node["attr"]["strides"]["list"]["i"][1])


def read_graph_model(json_path: str | Path) -> GraphModel:
    """Read ``model.json`` and its shards (beside it).

    Raises:
        ValueError: one line naming the file: not JSON, no manifest, a missing shard, a dtype or
            quantisation this reader does not know, or shard bytes that do not add up.
    """
    json_path = Path(json_path)
    try:
        spec = json.loads(json_path.read_text())
        groups = spec["weightsManifest"]
        nodes = spec["modelTopology"]["node"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{json_path}: not a TF.js graph model ({type(exc).__name__}: {exc})") from None
    weights: dict[str, np.ndarray] = {}
    quant: dict[str, str | None] = {}
    for group in groups:
        parts = []
        for p in group["paths"]:
            f = json_path.parent / p
            if not f.is_file():
                raise ValueError(f"{f}: weight shard of {json_path} is missing")
            parts.append(f.read_bytes())
        buf, off = b"".join(parts), 0
        for w in group["weights"]:
            shape = [int(s) for s in w["shape"]]
            n = int(np.prod(shape)) if shape else 1
            q = (w.get("quantization") or {}).get("dtype")
            if q is None:
                if w["dtype"] not in _PLAIN:
                    raise ValueError(
                        f"{json_path}: weight {w['name']} has dtype {w['dtype']!r}, not one of {sorted(_PLAIN)}"
                    )
                dt = np.dtype(_PLAIN[w["dtype"]])
            elif q in _QUANT:
                dt = np.dtype(_QUANT[q])
            else:
                raise ValueError(
                    f"{json_path}: weight {w['name']} is quantised as {q!r}, not one of {sorted(_QUANT)}"
                )
            if off + n * dt.itemsize > len(buf):
                raise ValueError(f"{json_path}: its shards end inside weight {w['name']} ({len(buf)} bytes)")
            arr = np.frombuffer(buf, dtype=dt, count=n, offset=off)
            if q == "float16":
                arr = arr.astype(np.float32)
            elif q in ("uint8", "uint16"):
                arr = arr.astype(np.float32) * float(w["quantization"]["scale"]) + float(
                    w["quantization"]["min"]
                )
            weights[w["name"]] = arr.reshape(shape).copy()
            quant[w["name"]] = q
            off += n * dt.itemsize
        if off != len(buf):
            raise ValueError(f"{json_path}: its shards hold {len(buf)} bytes, the manifest {off}")
    ops = [n for n in nodes if n["op"] != "Const"]
    return GraphModel(nodes=ops, weights=weights, quantization=quant)


def write_graph_model(
    json_path: str | Path,
    weights: dict[str, np.ndarray],
    nodes: list[dict[str, Any]] | None = None,
    float16: bool = True,
) -> Path:
    """Write weights as a TF.js graph model (one shard ``<stem>.bin``), float tensors as float16 when
    ``float16``: the inverse of :func:`read_graph_model`, for tests and tiny fixtures."""
    json_path = Path(json_path)
    shard = json_path.with_suffix(".bin")
    entries, blobs = [], []
    for name, arr in weights.items():
        arr = np.asarray(arr)
        e: dict[str, Any] = {"name": name, "shape": list(arr.shape)}
        if arr.dtype.kind == "f":
            e["dtype"] = "float32"
            if float16:
                e["quantization"] = {"dtype": "float16", "original_dtype": "float32"}
                blobs.append(arr.astype(np.float16).tobytes())
            else:
                blobs.append(arr.astype(np.float32).tobytes())
        elif arr.dtype.kind in "iu":
            e["dtype"] = "int32"
            blobs.append(arr.astype(np.int32).tobytes())
        else:
            raise ValueError(f"{name}: dtype {arr.dtype} cannot be written")
        entries.append(e)
    shard.write_bytes(b"".join(blobs))
    spec = {
        "format": "graph-model",
        "modelTopology": {"node": nodes or []},
        "weightsManifest": [{"paths": [shard.name], "weights": entries}],
    }
    json_path.write_text(json.dumps(spec))
    return json_path
