"""ONNX: the network as a self-contained ONNX model, checked against PyTorch on the spot.

Inputs: ``image [B, 3, H, W]`` float RGB in [0, 1] at any height and width (the network size the predict path
chooses, the same as PyTorch's); a model with a pose branch also takes ``prior [B, 4]`` (height m, pitch, roll, fov
deg; any value where unknown), ``prior_known [B, 4]`` (bool) and ``prior_sigma [B, 4]``, fused with the network's
pose before its IGD feature exactly as in PyTorch. Outputs are named as
:data:`~dapm_lightning.models.dapm.INFERENCE_OUTPUTS` (those the model has).
The file's metadata (:func:`export_metadata`) holds what prediction needs besides the graph: the network's
settings (depth kind, depth limit, IGD model, pose ranges), the training size, the pose order and units, the sky
threshold, the project version and the source checkpoint's hash. The ops that differ while exporting are defined
where the network uses them (:func:`dapm_lightning.models.blocks.adaptive_avg_pool2d`). PyTorch's exporter writes the
weights of a large model beside the graph, in ``NAME.onnx.data``: keep the two files together, the weights under
that name, which the graph records (:func:`external_data_files`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from dapm_lightning import __version__
from dapm_lightning.data.files import WRITE_ERRNOS, WriteError, is_full_disk, stops_deferred, write_error
from dapm_lightning.geometry.constants import POSE_KEYS, POSE_UNITS, SKY_PROBABILITY_THRESHOLD
from dapm_lightning.inference.inputs import SIZE_MULTIPLE, network_size
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.models.prior import PosePrior
from dapm_lightning.training.checkpoint_files import is_split_checkpoint, join_split_checkpoint

PRIOR_INPUTS = ("prior", "prior_known", "prior_sigma")
"""The exported inputs of a model with a pose branch, after ``image``: the values (finite; any value where
unknown), which are known (bool), and their σ. No NaN enters the graph, so int8 calibration sees none."""
CHECK_DRAW = "draw"
"""Key of a check row: ``(k, n)``, the k-th of the n random inputs checked at that shape."""
METADATA_NET = "dapm.net"
"""The metadata key that marks a dapm-lightning export: the network's settings as JSON."""
METADATA_WEIGHTS = "dapm.weights_sha256"
"""The SHA-256 of the exported network's weights (:func:`weights_digest`)."""
METADATA_ON_FIRST_USE = "dapm.exported_on_first_use"
"""Set in a file ``DAPMPredictor(onnx_path=...)`` exported itself: it may replace it when the weights change."""


class ExportWrapper(nn.Module):
    """``image`` (and, with a pose branch, ``prior``, ``prior_sigma``) -> the model's outputs, as a tuple.

    :attr:`names` lists the outputs this model has, among ``depth_m``, ``sky_prob``, ``pose`` (the pose used),
    ``pose_network`` (the network's own) and ``pose_spread`` (its bins spread); :attr:`input_names` its inputs.
    ``half``: the network runs in float16 (call after ``net.half()``); inputs and outputs stay float32.
    """

    def __init__(self, net: nn.Module, half: bool = False) -> None:
        super().__init__()
        self.net, self.half_precision = net, half
        config = getattr(net, "config", None)
        self.takes_prior = bool(getattr(config, "use_pose", False))
        self.input_names = ("image", *PRIOR_INPUTS) if self.takes_prior else ("image",)
        dtype = next(net.parameters()).dtype
        with torch.no_grad():
            out = self.forward_outputs(*example_inputs(1, (SIZE_MULTIPLE * 2, SIZE_MULTIPLE * 2), self.takes_prior,
                                                       dtype=dtype))
        self.names = tuple(out)
        self.eval()

    def forward_outputs(self, image: Tensor, prior: Tensor | None = None, prior_known: Tensor | None = None,
                        prior_sigma: Tensor | None = None) -> dict[str, Tensor]:
        """The outputs by name."""
        pose_prior = None
        if self.takes_prior and prior is not None and prior_known is not None and prior_sigma is not None:
            pose_prior = PosePrior(prior.float(), prior_sigma.float(), prior_known)
        out = self.net(image.half() if self.half_precision else image, prior=pose_prior)
        outputs = {name: value.float() for name, value in out.inference_outputs(spread=True).named().items()}
        if pose_prior is not None and "pose" in outputs:  # nothing known (eager skips the fusion): used = own
            outputs.setdefault("pose_network", outputs["pose"])
        return outputs

    def forward(self, image: Tensor, prior: Tensor | None = None, prior_known: Tensor | None = None,
                prior_sigma: Tensor | None = None) -> tuple[Tensor, ...]:
        outputs = self.forward_outputs(image, prior, prior_known, prior_sigma)
        return tuple(outputs[name] for name in self.names)


def onnx_feed(images: np.ndarray, input_names: Sequence[str],
              prior: PosePrior | None = None) -> dict[str, np.ndarray]:
    """An exported model's inputs by name.

    ``images`` ``[B, 3, H, W]`` float32 in [0, 1] and, when the model takes them, the prior's inputs (nothing known
    without one).
    """
    feed = {"image": images}
    if PRIOR_INPUTS[0] in input_names:
        batch = images.shape[0]
        value = prior.value.detach().cpu().float() if prior is not None else torch.zeros(batch, 4)
        known = prior.known.cpu() if prior is not None else torch.zeros(batch, 4, dtype=torch.bool)
        sigma = prior.sigma.detach().cpu().float().expand(batch, 4) if prior is not None else torch.zeros(batch, 4)
        feed.update({PRIOR_INPUTS[0]: torch.where(known, value, torch.zeros_like(value)).numpy(),
                     PRIOR_INPUTS[1]: known.numpy(), PRIOR_INPUTS[2]: sigma.contiguous().numpy()})
    return feed


def example_inputs(batch: int, size: tuple[int, int], takes_prior: bool, *, seed: int = 0,
                   dtype: torch.dtype = torch.float32) -> tuple[Tensor, ...]:
    """Random inputs: images, and priors with every component known in some images and unknown in others."""
    generator = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, *size, generator=generator).to(dtype)
    if not takes_prior:
        return (image,)
    prior = torch.tensor([40.0, -45.0, 0.0, 70.0]) + 5 * torch.randn(batch, 4, generator=generator)
    known = torch.rand(batch, 4, generator=generator) < 0.5
    sigma = torch.rand(batch, 4, generator=generator) * torch.tensor([3.0, 1.0, 1.0, 2.0])
    sigma = torch.where(torch.rand(batch, 4, generator=generator) < 0.5, sigma, torch.zeros_like(sigma))
    return image, torch.where(known, prior, torch.zeros_like(prior)), known, sigma


def check_sizes(size: tuple[int, int], dynamic: bool) -> list[tuple[int, int, int]]:
    """``(batch, H, W)`` of the inputs compared with PyTorch: the export size, and another aspect if dynamic."""
    sizes = [(1, *size)]
    if dynamic:
        sizes.append((2, max(SIZE_MULTIPLE, size[0] - 13), size[1] + 21))
    return sizes


def export_metadata(net: nn.Module, train_image_size: tuple[int, int] | None = None,
                    source: str | Path | None = None) -> dict[str, str]:
    """What an exported file says about itself: everything prediction needs besides the graph.

    Args:
        net: the :class:`~dapm_lightning.models.dapm.DAPMNet` (its :class:`DAPMConfig`).
        train_image_size: ``(H, W)`` it was trained at (the network size of prediction keeps its pixel count).
        source: the checkpoint it came from (its SHA-256 is recorded).
    """
    config: DAPMConfig = getattr(net, "config")  # noqa: B009 (an nn.Module attribute)
    igd = config.igd
    values = {METADATA_NET: json.dumps(config.to_dict(), sort_keys=True),
              "dapm.version": __version__,
              "dapm.train_image_size": json.dumps(list(train_image_size) if train_image_size else None),
              "dapm.pose_order": ",".join(POSE_KEYS),
              "dapm.pose_units": ",".join(POSE_UNITS[k] for k in POSE_KEYS),
              "dapm.depth_kind": igd.depth_kind, "dapm.max_depth_m": repr(igd.max_depth),
              "dapm.igd_model": igd.model, "dapm.sky_threshold": repr(SKY_PROBABILITY_THRESHOLD),
              "dapm.inputs": "image [B, 3, H, W] float RGB in [0, 1], any H and W"
                             + ("; prior [B, 4] (height m, pitch, roll, fov deg), prior_known [B, 4] bool, "
                                "prior_sigma [B, 4]" if config.use_pose else "")}
    values[METADATA_WEIGHTS] = weights_digest(net)
    if source is not None:
        data = join_split_checkpoint(source) if is_split_checkpoint(source) else Path(source).read_bytes()
        values["dapm.source_sha256"] = hashlib.sha256(data).hexdigest()  # a split folder: of the joined file
    return values


def weights_digest(net: nn.Module) -> str:
    """SHA-256 of a network's weights and buffers (names, types, shapes and values, in name order)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(net.state_dict().items()):
        digest.update(f"{name} {tensor.dtype} {tuple(tensor.shape)}\n".encode())
        digest.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def read_metadata(path: str | Path) -> dict[str, str]:
    """An ONNX file's metadata properties (its weights file is not read)."""
    import onnx

    return {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}


def write_metadata(path: str | Path, metadata: Mapping[str, str]) -> None:
    """Set ``metadata`` as the ONNX file's metadata properties (the weights file beside it is left as it is)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    kept = {p.key: p.value for p in model.metadata_props if p.key not in metadata}
    del model.metadata_props[:]
    for key, value in {**kept, **metadata}.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(path))


MAX_EXPORT_SIDE = 8192
"""The largest height or width an exported graph takes (and may be exported at)."""


def export_onnx(net: nn.Module, path: str | Path, size: tuple[int, int], *, checks: int = 3, seed: int = 0,
                dynamic: bool = True, fp16: bool = False,
                metadata: Mapping[str, str] | None = None) -> list[dict[str, Any]]:
    """Export ``net`` (a :class:`DAPMNet`) and compare onnxruntime with PyTorch (float32) on random inputs.

    Args:
        net: the network (left unchanged). path: the ``.onnx`` file. size: ``(H, W)`` of the example input.
        checks: random inputs per checked size. dynamic: dynamic batch, height and width (any size).
        fp16: half-precision weights and arithmetic.
        metadata: written into the file (:func:`export_metadata`; default: from ``net`` alone).

    Returns:
        one row per random input: ``shape`` and the max absolute difference of each output (``depth_m`` in
        metres, ``pose`` in metres/degrees).
    """
    import copy

    import onnxruntime

    reference = ExportWrapper(net.eval())
    model = ExportWrapper(copy.deepcopy(net).eval().half(), half=True) if fp16 else reference
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # torch.export specialises what the example makes look constant: a batch of 1 to 1, and sides that divide by
    # the strides to expressions true only for such sides; a batch of 2 and odd sides keep the graph general
    # (odd, and within the range of sides the graph is exported for: 8192 is traced at 8191)
    top = MAX_EXPORT_SIDE - 1
    traced = (min(size[0] | 1, top), min(size[1] | 1, top)) if dynamic else size
    example = example_inputs(2 if dynamic else 1, traced, model.takes_prior, seed=seed)
    dynamic_shapes = None
    if dynamic:
        batch = torch.export.Dim("batch", min=1, max=4096)
        height = torch.export.Dim("height", min=SIZE_MULTIPLE, max=MAX_EXPORT_SIDE)
        width = torch.export.Dim("width", min=SIZE_MULTIPLE, max=MAX_EXPORT_SIDE)
        dynamic_shapes = {"image": {0: batch, 2: height, 3: width}}
        dynamic_shapes.update({name: {0: batch} for name in model.input_names[1:]})
    with torch.no_grad(), warnings.catch_warnings():  # the network's export-time ops: models.blocks
        # the image's batch and each prior's are one dimension: the exporter's note that it merged their names
        warnings.filterwarnings("ignore", message=".*will not be used, since it shares the same shape constraints")
        torch.onnx.export(model, example, str(path), input_names=list(model.input_names),
                          output_names=list(model.names), dynamo=True, dynamic_shapes=dynamic_shapes, verbose=False)
    write_metadata(path, metadata if metadata is not None else export_metadata(net))
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rows = []
    for index, shape in enumerate(check_sizes(size, dynamic)):
        for check in range(checks):
            inputs = example_inputs(shape[0], shape[1:], model.takes_prior, seed=seed + 1 + 100 * index + check)
            with torch.no_grad():
                expected = reference(*inputs)
            got = session.run(None, {name: value.numpy() for name, value in zip(model.input_names, inputs)})
            row: dict[str, Any] = {"shape": shape, CHECK_DRAW: (check + 1, checks),
                                   **{name: float(output_difference(g, e.numpy()).max())
                                      for name, g, e in zip(model.names, got, expected)}}
            if "depth_m" in model.names:
                depth, reference_depth = got[model.names.index("depth_m")], expected[model.names.index("depth_m")]
                relative = output_difference(depth, reference_depth.numpy()) / np.fmax(reference_depth.numpy(), 1e-3)
                row[DEPTH_SHARE_OFF] = float((relative > 0.01).mean())
            rows.append(row)
    return rows


DEPTH_SHARE_OFF = "depth_share_off_1pct"
"""Key of an :func:`export_onnx` row: the share of pixels whose ONNX depth differs from PyTorch's by more than 1 %."""
EXPORT_TOLERANCES = {False: {DEPTH_SHARE_OFF: 1e-3, "sky_prob": 0.01, "pose": 0.05, "pose_network": 0.05},
                     True: {DEPTH_SHARE_OFF: 1e-2, "sky_prob": 0.15, "pose": 0.5, "pose_network": 0.5}}
"""The most an exported model may differ from PyTorch on :func:`export_onnx`'s checks, float32 (False) and float16
(True): the share of depth pixels off by more than 1 %, the sky probability, the pose (m or deg)."""


def output_difference(got: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """``|got - expected|`` per element: 0 where both are NaN (or the same infinity), inf where only one is NaN."""
    with np.errstate(invalid="ignore"):
        difference = np.where((got == expected) | (np.isnan(got) & np.isnan(expected)), 0.0, np.abs(got - expected))
    return np.nan_to_num(difference, nan=np.inf)


def export_mismatches(rows: Sequence[Mapping[str, Any]], fp16: bool = False) -> list[str]:
    """The checks of :func:`export_onnx` that exceed :data:`EXPORT_TOLERANCES`, each as a sentence (NaN exceeds)."""
    failures = []
    for key, limit in EXPORT_TOLERANCES[fp16].items():
        worst = max((row for row in rows if key in row), key=lambda row: np.nan_to_num(row[key], nan=np.inf),
                    default=None)
        if worst is not None and not worst[key] <= limit:
            failures.append(f"{key} {worst[key]:.3g} > {limit:g} at {tuple(worst['shape'])}")
    return failures


def weights_file(path: str | Path) -> Path:
    """Where the exporter puts a large model's weights: ``NAME.onnx.data`` beside ``NAME.onnx``."""
    return Path(path).with_name(Path(path).name + ".data")


def external_data_files(path: str | Path) -> list[str]:
    """The weights files an ONNX file's graph names (relative to its folder), in order of first use.

    The name is recorded inside the ``.onnx`` when it is written (``NAME.onnx.data`` of the exported ``NAME``):
    renaming or copying the ``.onnx`` does not change it. Empty when the weights are inside the file, or the file
    (or the ``onnx`` package) cannot be read.
    """
    return list(external_data_extents(path))


def external_data_extents(path: str | Path) -> dict[str, int]:
    """Each weights file the graph names (:func:`external_data_files`, same order), with the bytes it must hold.

    Those are the end of the last tensor the graph reads from it.
    """
    try:
        import onnx

        model = onnx.load(str(path), load_external_data=False)
    except Exception:  # noqa: BLE001 - no onnx package, or not an ONNX file: nothing to say
        return {}
    extents: dict[str, int] = {}

    def tensors(graph: Any) -> Iterator[Any]:
        yield from graph.initializer
        for node in graph.node:
            for attribute in node.attribute:
                yield from [attribute.t] if attribute.HasField("t") else []
                yield from attribute.tensors
                for sub in ([attribute.g] if attribute.HasField("g") else []) + list(attribute.graphs):
                    yield from tensors(sub)

    for tensor in tensors(model.graph):
        if tensor.data_location == onnx.TensorProto.EXTERNAL:
            entries = {entry.key: entry.value for entry in tensor.external_data}
            location = entries.get("location")
            if location:
                end = int(entries.get("offset", 0) or 0) + int(entries.get("length", 0) or 0)
                extents[location] = max(extents.get(location, 0), end)
    return extents


def missing_weights_message(path: Path) -> str | None:
    """Why ``path`` cannot load, with the fix, when a weights file its graph names is missing or short; else None."""
    extents = external_data_extents(path)
    missing = [name for name in extents if not (path.parent / name).is_file()]
    short = [(name, (path.parent / name).stat().st_size, end) for name, end in extents.items()
             if name not in missing and (path.parent / name).stat().st_size < end]
    if short:
        name, size, end = short[0]
        return (f"{path}: its weights file {path.parent / name} is cut short: {size:,} bytes, where the graph reads "
                f"{end:,} (a copy or download that stopped, or a full disk).\nFix: copy the .onnx and its weights "
                f"file again together, or export again: dapm-lightning export CKPT --out {path}")
    if not missing:
        return None
    wanted = path.parent / missing[0]
    renamed = weights_file(path)
    unused = f" ({renamed.name} beside it is not read)" if renamed.is_file() and renamed != wanted else ""
    return (f"{path}: its weights file {wanted} is missing. An exported model records its weights file's name "
            f"inside the .onnx ({missing[0]}): renaming the .onnx and its .data file does not change it{unused}.\n"
            f"Fix: keep the weights file beside it under its original name, {wanted}, or export again under the new "
            f"name: dapm-lightning export CKPT --out {path} (writes {path.name} and {renamed.name})")


def move_exported(staged: Path, final: Path) -> None:
    """Move an export (its graph and, where there is one, its weights file) from ``staged`` to ``final``.

    Two renames that must agree: SIGTERM and Ctrl-C wait until both are done (:func:`stops_deferred`), so a stop
    never leaves an earlier export's graph reading this export's weights.
    """
    staged_data, final_data = weights_file(staged), weights_file(final)
    with stops_deferred():
        if staged_data.is_file():
            os.replace(staged_data, final_data)
        else:
            final_data.unlink(missing_ok=True)  # an earlier export's weights, not this graph's
        os.replace(staged, final)


def ensure_exported(module: nn.Module, path: Path) -> Path:
    """``path``, exported from ``module`` (dynamic sizes, checked, with its metadata) unless it holds its weights.

    Exported into a hidden folder beside ``path`` and moved there once checked: an export interrupted or refused
    leaves no file that a later call would take as exported and checked. A file there exported from other weights
    or settings (the model retrained since) is replaced when an earlier call wrote it, refused when it came from
    elsewhere (``dapm-lightning export``, another tool), which this never overwrites.

    Raises:
        FileExistsError: ``path`` holds another model this did not export.
    """
    net = getattr(module, "net", module).eval()
    if path.is_file():
        try:
            recorded = read_metadata(path)
        except Exception:  # protobuf's DecodeError: not an ONNX file, or one cut short
            recorded = {}
        config: DAPMConfig = getattr(net, "config")  # noqa: B009 (an nn.Module attribute)
        if (recorded.get(METADATA_WEIGHTS) == weights_digest(net)
                and recorded.get(METADATA_NET) == json.dumps(config.to_dict(), sort_keys=True)):
            return path  # the same weights and settings (a changed max_depth alone changes what the file says)
        if recorded.get(METADATA_ON_FIRST_USE) != "true":
            if METADATA_NET not in recorded:
                what = ("not a dapm-lightning export (not an ONNX model, one cut short, or another tool's), so it is "
                        "not replaced")
            elif METADATA_WEIGHTS not in recorded:
                what = ("an export that records no weights digest (dapm.weights_sha256: exported by an older "
                        "dapm-lightning), so whether it holds this checkpoint's weights is unknown; it is not replaced")
            else:
                what = ("an exported model of other weights or settings than this checkpoint's, not written by "
                        "onnx_path (dapm-lightning export or another tool), so it is not replaced")
            raise FileExistsError(f"{path}: {what}.\nFix: give another onnx_path, delete that file (onnx_path then "
                                  "exports this checkpoint there), or run it on its own with "
                                  "DAPMPredictor.from_checkpoint(its path)")
    trained = getattr(module, "train_image_size", None)
    size = network_size(int(trained[0]), int(trained[1]), (int(trained[0]), int(trained[1]))) if trained \
        else (64, 64)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:  # the graph records its weights file's name: the staged file has the final name
        failures = export_mismatches(export_onnx(net, staging / path.name, size, checks=1, dynamic=True,
                                                 metadata={**export_metadata(net, trained),
                                                           METADATA_ON_FIRST_USE: "true"}))
        if not failures:
            move_exported(staging / path.name, path)
    except OSError as error:  # a full disk while exporting: the model's file named, not the staging folder's
        if isinstance(error, WriteError) or (error.errno not in WRITE_ERRNOS and not is_full_disk(error)):
            raise
        raise write_error(path, error) from error
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    if failures:  # never run a model that disagrees with the network it came from
        raise RuntimeError(f"{path}: the exported model disagrees with PyTorch ({'; '.join(failures)}); not "
                           "written. Fix: predict with the PyTorch runtime, and report this as a bug of the export")
    return path
