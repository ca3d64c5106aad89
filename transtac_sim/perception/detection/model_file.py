"""The detector's model file: a PyTorch checkpoint (``.pt``) holding MarkerNet's weights and what is needed
to use them (format tag and version, network width, the image sizes it was trained on, how it was made),
and its ONNX export (same name, ``.onnx``) for onnxruntime on the CPU.

Files are written atomically; loading checks the format tag and says clearly when a file is not a
detector model.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import torch

from transtac_sim.perception.detection.network import MarkerNet
from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.writer.atomic import atomic_write

FORMAT = "transtac_marker_detector"
VERSION = 1
#: the model shipped with the repository (README, "Detection and tracking")
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "markernet_default.pt"


def save_model(path: Path, net: MarkerNet, image_sizes: list[tuple[int, int]], provenance: dict) -> Path:
    """Write ``path`` (.pt) and its ONNX export ``path.with_suffix('.onnx')``."""
    payload = {"format": FORMAT, "version": VERSION, "width": net.width, "context": net.context,
               "image_sizes": [list(s) for s in image_sizes], "provenance": provenance,
               "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}
    atomic_write(Path(path), lambda f: torch.save(payload, f))
    export_onnx(net, Path(path).with_suffix(".onnx"), image_sizes[0])
    return Path(path)


def export_onnx(net: MarkerNet, path: Path, image_size: tuple[int, int]) -> Path:
    """ONNX graph of the network (outputs: heatmap logits, offset, size) with free batch, height and width."""
    w, h = image_size
    net = net.cpu().eval()
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter: no onnxscript needed
        torch.onnx.export(_Heads(net), torch.zeros(1, 3, h, w), buf, input_names=["image"],
                          output_names=["heatmap", "offset", "size"], opset_version=17, dynamo=False,
                          dynamic_axes={"image": {0: "n", 2: "h", 3: "w"}, "heatmap": {0: "n", 2: "h2", 3: "w2"},
                                        "offset": {0: "n", 2: "h2", 3: "w2"}, "size": {0: "n", 2: "h2", 3: "w2"}})
    return atomic_write(path, lambda f: f.write(buf.getvalue()))


class _Heads(torch.nn.Module):
    """MarkerNet without the feature output (what inference needs)."""

    def __init__(self, net: MarkerNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x):
        heat, offset, size, _ = self.net(x)
        return heat, offset, size


def load_model(path: Path) -> tuple[MarkerNet, dict]:
    """The network (eval mode, CPU) and the file's metadata. Raises PerceptionInputError for a missing file or
    one that is not a detector model of a known version."""
    path = Path(path)
    fix = "pass a model written by `transtac-sim train-detector` (or leave --model out for the shipped one)"
    if not path.is_file():
        raise PerceptionInputError(path, "model file not found", fix)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # pickle, zip or torch errors: the file is not a checkpoint
        raise PerceptionInputError(path, f"not a detector model ({type(e).__name__})", fix) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise PerceptionInputError(path, "not a detector model (no 'transtac_marker_detector' tag)", fix)
    if payload.get("version") != VERSION:
        raise PerceptionInputError(path, f"detector model version {payload.get('version')}, this code reads {VERSION}",
                                   "retrain it with this version")
    net = MarkerNet(width=int(payload["width"]), context=bool(payload.get("context", False)))
    net.load_state_dict(payload["state_dict"])
    meta = {k: v for k, v in payload.items() if k != "state_dict"}
    meta["image_sizes"] = [tuple(s) for s in meta["image_sizes"]]
    return net.eval(), meta
