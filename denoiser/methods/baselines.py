"""Methods compared by evaluation and the benchmark, all behind one per-frame interface.

A *method* is called frame by frame, in sequence order::

    method.reset()                                  # before a new sequence
    output = method(frame, reset)                   # frame: dict of [1, C, H, W] tensors

``frame`` holds ``color [1, 3, H, W]`` (noisy linear HDR), ``albedo [1, 3, H, W]``,
``normal [1, 3, H, W]``, ``depth [1, 1, H, W]``, ``motion [1, 2, H, W]``; ``reset`` is True on
the first frame of a sequence and at camera cuts. ``output`` is ``[1, 3, H, W]`` linear HDR.

* :class:`NoisyInput` returns the noisy color (the "no denoiser" baseline);
* :class:`OidnDenoiser` is Intel Open Image Denoise (``pyoidn``, RT filter, ``hdr=True``, with
  albedo and normal) at quality ``fast``, ``balanced`` or ``high``, on a CPU device whose
  thread count is set explicitly (``numThreads``), by default to ``torch.get_num_threads()``
  so OIDN and PyTorch get the same cores. OIDN is a single-frame denoiser: ``reset`` is ignored;
* :class:`NetworkMethod` runs a trained :class:`~denoiser.nn.denoiser.Denoiser` recurrently
  through :class:`~denoiser.recurrent.RecurrentRunner` (state carried, discarded at resets).

OIDN input conventions: color is clamped to >= 0 (HDR input must be non-negative), albedo to
[0, 1] (OIDN's documented range; some renderers exceed 1), normals are passed as they are
(OIDN accepts world- or view-space unit normals; ours are camera space).
"""

from __future__ import annotations

import contextlib
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
import torch

from denoiser.errors import ConfigError
from denoiser.measure import StagedStep
from denoiser.recurrent import Method, Network, RecurrentRunner, is_network

#: OIDN quality names -> pyoidn constants (resolved lazily, pyoidn is an optional extra)
OIDN_QUALITIES = ("fast", "balanced", "high")


class NoisyInput:
    """The noisy input itself: the "no denoising" baseline."""

    recurrent = False

    def __init__(self, label: str = "noisy input"):
        self.label = label

    def reset(self) -> None:
        """Nothing to reset."""

    def __call__(self, frame: dict, reset: bool = False) -> torch.Tensor:
        """``frame["color"]`` ``[1, 3, H, W]`` -> the same tensor (float32)."""
        return frame["color"].float()


def _hwc(x: torch.Tensor) -> np.ndarray:
    """``[1, C, H, W]`` tensor -> contiguous float32 ``[H, W, C]`` array."""
    return np.ascontiguousarray(x[0].detach().float().cpu().permute(1, 2, 0).numpy())


class OidnDenoiser:
    """Intel Open Image Denoise through ``pyoidn`` on the CPU (see module docstring).

    Args:
        quality: ``fast``, ``balanced`` or ``high``.
        threads: OIDN ``numThreads``; None uses ``torch.get_num_threads()`` (same as torch).
        use_aux: pass albedo and normal (True) or color only.
        label: display name (default ``OIDN-<quality>``).

    The device and filter are created once; the filter is re-committed only when the frame
    size changes (commit is OIDN's set-up step: it is not part of the per-frame cost).
    """

    recurrent = False

    def __init__(self, quality: str = "high", threads: int | None = None, use_aux: bool = True,
                 label: str | None = None):
        if quality not in OIDN_QUALITIES:
            raise ConfigError(f"OIDN quality {quality!r} is not one of {', '.join(OIDN_QUALITIES)}")
        import pyoidn.filter as oidn_filter
        from pyoidn.device import Device

        self.quality = quality
        self.use_aux = bool(use_aux)
        self.threads = int(threads) if threads else torch.get_num_threads()
        self.label = label or f"OIDN-{quality}"
        self._consts = oidn_filter
        self._device = Device()
        self._device.set_int("numThreads", self.threads)
        self._device.commit()
        self._check("device creation")
        self._filter = None
        self._size: tuple[int, int] | None = None
        self._images: dict[str, np.ndarray] = {}

    def _check(self, what: str) -> None:
        err = self._device.get_error()
        if err:
            raise RuntimeError(f"OIDN {what} failed: {err}")

    def _setup(self, h: int, w: int) -> None:
        """(Re)create the shared images and commit the filter for an ``h`` x ``w`` frame."""
        c = self._consts
        if self._filter is not None:
            self._filter.release()
        names = ["color", "output"] + (["albedo", "normal"] if self.use_aux else [])
        self._images = {n: np.zeros((h, w, 3), dtype=np.float32) for n in names}
        flt = c.Filter(self._device, c.OIDN_FILTER_TYPE_RT)
        for n, arr in self._images.items():
            flt.set_image(n, arr, c.OIDN_FORMAT_FLOAT3)
        flt.set_bool("hdr", True)
        flt.set_quality({"fast": c.OIDN_QUALITY_FAST, "balanced": c.OIDN_QUALITY_BALANCED,
                         "high": c.OIDN_QUALITY_HIGH}[self.quality])
        flt.commit()
        self._filter = flt
        self._size = (h, w)
        self._check("filter commit")

    def threads_in_use(self) -> int:
        """The device's ``numThreads`` as OIDN reports it."""
        return int(self._device.get_int("numThreads"))

    def reset(self) -> None:
        """OIDN has no temporal state."""

    def denoise_arrays(self, color: np.ndarray, albedo: np.ndarray | None = None,
                       normal: np.ndarray | None = None) -> np.ndarray:
        """Denoise ``[H, W, 3]`` float32 arrays; returns a new ``[H, W, 3]`` array."""
        h, w = color.shape[:2]
        if self._size != (h, w):
            self._setup(h, w)
        np.maximum(color, 0.0, out=self._images["color"])
        if self.use_aux:
            if albedo is None or normal is None:
                raise ConfigError("OIDN with use_aux=true needs albedo and normal buffers")
            np.clip(albedo, 0.0, 1.0, out=self._images["albedo"])
            self._images["normal"][...] = normal
        self._filter.execute()
        self._check("execution")
        return self._images["output"].copy()

    def __call__(self, frame: dict, reset: bool = False) -> torch.Tensor:
        """Denoise one frame (``[1, C, H, W]`` tensors) -> ``[1, 3, H, W]`` float32."""
        out = self.denoise_arrays(_hwc(frame["color"]),
                                  _hwc(frame["albedo"]) if self.use_aux else None,
                                  _hwc(frame["normal"]) if self.use_aux else None)
        return torch.from_numpy(out).permute(2, 0, 1)[None].to(frame["color"].device)

    def close(self) -> None:
        """Release the OIDN filter and device."""
        if self._filter is not None:
            self._filter.release()
            self._filter = None
        if self._device is not None:
            self._device.release()
            self._device = None

    def __del__(self):  # pragma: no cover - best effort at interpreter exit
        with contextlib.suppress(Exception):
            self.close()


class NetworkMethod:
    """A trained denoiser run recurrently, frame by frame, with its state carried.

    Args:
        net: a :class:`~denoiser.recurrent.Network` module (eval mode is set here).
        label: display name.
        device: torch device to run on; frames are moved there.
    """

    recurrent = True

    def __init__(self, net: Network, label: str, device: str | torch.device = "cpu"):
        if not is_network(net) or not isinstance(net, torch.nn.Module):
            raise ConfigError(f"{label}: a {type(net).__name__} is not a denoising network module "
                              "(denoiser.recurrent.Network: step, feature_channels, multiple, temporal)")
        self.net = net.eval().to(device)
        self.label = label
        self.device = torch.device(device)
        self.runner = RecurrentRunner(self.net.step)

    def reset(self) -> None:
        """Forget the history (next frame starts a sequence)."""
        self.runner.reset()

    @torch.no_grad()
    def __call__(self, frame: dict, reset: bool = False) -> torch.Tensor:
        """One recurrent step: ``frame`` ``[1, C, H, W]`` tensors -> ``[1, 3, H, W]`` float32."""
        inputs = {k: v.to(self.device) for k, v in frame.items() if isinstance(v, torch.Tensor)}
        return self.runner(inputs, reset).float()


class StepperMethod:
    """A backend's prepared network (:class:`~denoiser.recurrent.Stepper`: eager, ONNX Runtime,
    OpenVINO f32/bf16, ...) as an evaluation method, stepped through the recurrent runner, so
    its quality is measured through the same backend and precision as its time
    (``denoiser-bench``). Outputs come back as ``[1, 3, H, W]`` float32 CPU tensors."""

    recurrent = True

    def __init__(self, stepper, label: str):
        self.label = label
        self.runner = RecurrentRunner(stepper.step)

    def reset(self) -> None:
        """Forget the history (next frame starts a sequence)."""
        self.runner.reset()

    def __call__(self, frame: dict, reset: bool = False) -> torch.Tensor:
        out = self.runner(frame, reset)
        if not isinstance(out, torch.Tensor):
            out = torch.from_numpy(np.array(out, dtype=np.float32))
        return out.detach().float().cpu()


def build_baselines(nodes) -> OrderedDict[str, Method]:
    """The methods of a ``baselines`` config node (``{key: {_target_: ...} | None}``, see
    ``conf/baselines/default.yaml``), in order, by their ``label``; None entries are skipped.
    A target that is not a :class:`~denoiser.recurrent.Method` is a one-line ConfigError naming its key."""
    from denoiser.configs import instantiate_config

    methods: OrderedDict[str, Method] = OrderedDict()
    for key, node in (nodes or {}).items():
        if node is not None:
            method = instantiate_config(node, f"baselines.{key}")
            if not isinstance(method, Method):
                missing = [m for m in ("label", "recurrent", "reset", "__call__") if not hasattr(method, m)]
                raise ConfigError(f"baselines.{key}: a {type(method).__name__} is not an evaluation method "
                                  f"(denoiser.recurrent.Method); it lacks {', '.join(missing)}")
            methods[method.label] = method
    return methods


# ----------------------------------------------------------------------------- timing OIDN (denoiser-bench)


def oidn_dtype(isa: dict[str, bool]) -> str:
    """The precision OIDN's CPU device computes in here: fp16 with AMX-FP16 (OIDN >= 2.4), else fp32."""
    return "fp16" if isa.get("amx_fp16") else "fp32"



def oidn_harness_steps(method, frames: list[dict]) -> StagedStep:
    """The benchmark's path to an OIDN baseline: each frame's buffers are put in OIDN's ``[H, W, 3]``
    layout before the clock starts (our frames are planar ``[1, C, H, W]``; a renderer hands OIDN
    interleaved pixels), the timed call is ``method.denoise_arrays`` (the clamping copies into
    OIDN's shared images, the filter, the output copy)."""
    def stage(k: int):
        frame = frames[k % len(frames)]
        arrays = [_hwc(frame[b]) for b in ("color", "albedo", "normal")]
        return lambda: method.denoise_arrays(*arrays)

    return stage



def oidn_direct_steps(quality: str, threads: int, frames: list[dict]) -> tuple[StagedStep, Callable[[], int], Callable[[], None]]:
    """OIDN called directly through pyoidn, the reference for the harness's OIDN path: one device
    (``numThreads`` = ``threads``) and one RT filter (``hdr``, ``quality``) bound once to four
    ``[H, W, 3]`` float32 arrays; staging writes frame ``k`` into them (clamped as the baseline
    clamps) untimed, the timed call is ``filter.execute()`` alone: no copies.

    Returns ``(entry, threads read back, close)``."""
    import pyoidn.filter as oidn_filter
    from pyoidn.device import Device

    h, w = frames[0]["color"].shape[-2:]
    images = {n: np.zeros((h, w, 3), np.float32) for n in ("color", "albedo", "normal", "output")}
    device = Device()
    device.set_int("numThreads", int(threads))
    device.commit()
    flt = oidn_filter.Filter(device, oidn_filter.OIDN_FILTER_TYPE_RT)
    for name, arr in images.items():
        flt.set_image(name, arr, oidn_filter.OIDN_FORMAT_FLOAT3)
    flt.set_bool("hdr", True)
    flt.set_quality({"fast": oidn_filter.OIDN_QUALITY_FAST, "balanced": oidn_filter.OIDN_QUALITY_BALANCED,
                     "high": oidn_filter.OIDN_QUALITY_HIGH}[quality])
    flt.commit()
    if device.get_error():
        raise RuntimeError(f"OIDN (direct) set-up failed: {device.get_error()}")

    def stage(k: int):
        frame = frames[k % len(frames)]
        np.maximum(_hwc(frame["color"]), 0.0, out=images["color"])
        np.clip(_hwc(frame["albedo"]), 0.0, 1.0, out=images["albedo"])
        images["normal"][...] = _hwc(frame["normal"])
        return flt.execute

    def close():
        flt.release()
        device.release()

    threads_used = int(device.get_int("numThreads"))  # read back once: close() releases the device
    return stage, lambda: threads_used, close
