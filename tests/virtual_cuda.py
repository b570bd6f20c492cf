"""CUDA placement checked on a machine without a GPU.

Inside ``virtual_cuda()`` every tensor stays in CPU memory, but each carries the device it would be on: a tensor
made with ``device="cuda"``, moved by ``.to("cuda")`` / ``.cuda()``, or computed from such a tensor is on the
virtual GPU, ``.device`` says ``cuda:0``, and ``.cpu()`` gives a copy back. What PyTorch refuses on a real GPU is
refused here with the same message: an operation that mixes a tensor on the GPU with a CPU tensor of one or more
dimensions (CPU scalars are allowed, as by PyTorch), and ``.numpy()`` of a tensor on the GPU. So a code path that
would fail with "Expected all tensors to be on the same device" on CUDA fails the same way in CI.

What it does not model: speed, float32 rounding on the GPU, the few operations that PyTorch lets mix devices
beyond indexing and copies, ``nn.Parameter``s moved by ``Module.to`` (they keep their identity and so their
CPU mark; rcotorch's blocks hold buffers only). Modes are per thread: threads started inside ``virtual_cuda()``
(the figures' drawing thread) enter it too, threads started before it do not.
"""

from __future__ import annotations

import contextlib
import threading
from unittest import mock

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten
from torch.utils.weak import WeakIdKeyDictionary

GPU = torch.device("cuda", 0)
CPU = torch.device("cpu")

# Operations that accept tensors on both devices (copies and indexing by CPU indices).
MIXED_OK = {"copy_", "to", "__getitem__", "__setitem__", "index_put_", "set_", "cpu", "cuda", "type",
            "_has_compatible_shallow_copy_type"}
INPLACE = {"__setitem__", "__iadd__", "__isub__", "__imul__", "__itruediv__", "__ifloordiv__", "__imod__",
           "__ipow__", "__iand__", "__ior__", "__ixor__", "__ilshift__", "__irshift__", "__imatmul__"}
FACTORIES = {"zeros", "ones", "empty", "full", "arange", "tensor", "as_tensor", "eye", "linspace", "logspace",
             "randn", "rand", "randint", "zeros_like", "ones_like", "empty_like", "full_like", "rand_like",
             "randn_like", "new_zeros", "new_ones", "new_empty", "new_full", "new_tensor", "scalar_tensor",
             "empty_strided", "tril_indices", "triu_indices"}


def _is_gpu(device) -> bool | None:
    if device is None:
        return None
    if isinstance(device, int):
        return True
    return torch.device(device).type == "cuda"


class VirtualCuda(TorchFunctionMode):
    # One mark table for every use, so that a tensor a cache keeps from an earlier use keeps its device.
    gpu = WeakIdKeyDictionary()

    def on_gpu(self, t) -> bool:
        return isinstance(t, torch.Tensor) and self.gpu.get(t, False)

    def mark(self, out, gpu: bool):
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor):
                if gpu:
                    self.gpu[t] = True
                else:
                    self.gpu.pop(t, None)
        return out

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        name = getattr(func, "__name__", "")
        if func == torch.Tensor.device.__get__:
            return GPU if self.on_gpu(args[0]) else CPU
        if func == torch.Tensor.is_cuda.__get__:
            return self.on_gpu(args[0])
        if func == torch.Tensor.is_cpu.__get__:
            return not self.on_gpu(args[0])
        if name == "get_device":
            return 0 if self.on_gpu(args[0]) else -1
        if name in ("numpy", "__array__") and self.on_gpu(args[0]):
            raise TypeError("can't convert cuda:0 device type tensor to numpy. Use Tensor.cpu() to copy the "
                            "tensor to host memory first.")
        if name == "cpu":
            t = args[0]
            return self.mark(t.clone(), False) if self.on_gpu(t) else t
        if name == "cuda":
            t = args[0]
            return t if self.on_gpu(t) else self.mark(t.clone(), True)
        if name == "to":
            return self._to(func, args, kwargs)
        if name in FACTORIES:
            want = _is_gpu(kwargs.pop("device", None))
            out = func(*args, **kwargs)
            if want is None:      # *_like, new_* and as_tensor keep the device of their first argument
                want = bool(args) and self.on_gpu(args[0]) and (name.endswith("_like") or name.startswith("new_")
                                                                 or name == "as_tensor")
            if args and out is args[0] and want != self.on_gpu(out):
                out = out.clone()                  # as_tensor to another device: a copy there
            return self.mark(out, want)
        tensors = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        gpu = [self.on_gpu(t) for t in tensors]
        if any(gpu) and name not in MIXED_OK:
            if any(not g and t.dim() > 0 for g, t in zip(gpu, tensors)):
                raise RuntimeError(f"Expected all tensors to be on the same device, but found at least two "
                                   f"devices, cuda:0 and cpu! (in {name}: "
                                   + ", ".join(f"{tuple(t.shape)} on {'cuda' if g else 'cpu'}"
                                               for g, t in zip(gpu, tensors)) + ")")
        out = func(*args, **kwargs)
        if (name.endswith("_") and not name.startswith("__")) or name in INPLACE:
            return out                                  # in place: the tensor keeps its device
        return self.mark(out, any(gpu)) if any(gpu) else out

    def _to(self, func, args, kwargs):
        t, rest = args[0], list(args[1:])
        target = None
        if kwargs.get("device") is not None:
            target, kwargs["device"] = _is_gpu(kwargs["device"]), "cpu"
        for i, a in enumerate(rest):
            if isinstance(a, torch.Tensor):
                target = self.on_gpu(a)
            elif isinstance(a, (str, torch.device)) or (isinstance(a, int) and not isinstance(a, bool)):
                target, rest[i] = _is_gpu(a), "cpu"
        out = func(t, *rest, **kwargs)
        src = self.on_gpu(t)
        if target is None or target == src:
            return self.mark(out, src) if out is not t else out
        if out is t:
            out = t.clone()
        return self.mark(out, target)


@contextlib.contextmanager
def virtual_cuda():
    """Run the body as if a CUDA device were present (see the module's docstring)."""
    with contextlib.ExitStack() as stack:
        for name, value in (("is_available", lambda: True), ("device_count", lambda: 1),
                            ("synchronize", lambda *a, **k: None), ("get_device_name", lambda *a: "virtual"),
                            ("max_memory_allocated", lambda *a, **k: 0), ("memory_allocated", lambda *a, **k: 0),
                            ("reset_peak_memory_stats", lambda *a, **k: None),
                            ("current_device", lambda: 0), ("empty_cache", lambda: None)):
            stack.enter_context(mock.patch.object(torch.cuda, name, value))
        plain_run = threading.Thread.run

        def run(self):
            with VirtualCuda():
                plain_run(self)
        stack.enter_context(mock.patch.object(threading.Thread, "run", run))
        stack.enter_context(VirtualCuda())
        yield
