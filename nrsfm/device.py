"""Which torch device a computation runs on: one rule for the solvers and the networks."""

from __future__ import annotations

import numpy as np

from nrsfm.errors import ValidationError


def pick_device(name: str = "auto"):
    """The ``torch.device`` for ``name``: ``"auto"`` is CUDA when torch sees a GPU, else the CPU; ``"cpu"``,
    ``"cuda"`` and ``"cuda:N"`` are taken as given.

    Raises:
        ValidationError: ``name`` is no device torch knows, or names a GPU this machine does not have.
    """
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as exc:
        raise ValidationError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}") from exc
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValidationError(f"device: {name!r} asked for, but torch sees no CUDA GPU on this machine; "
                                  "use device=cpu or device=auto")
        if device.index is not None and device.index >= count:
            raise ValidationError(f"device: {name!r} asked for, but torch sees {count} CUDA GPU(s) "
                                  f"(cuda:0..cuda:{count - 1})")
    elif device.type != "cpu":
        raise ValidationError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}")
    return device


def indices_to(indices, device):
    """`(B,)` minibatch indices (a numpy array) as a tensor on ``device``; to a GPU from pinned memory without
    waiting for the work already queued there."""
    import torch

    idx = torch.from_numpy(np.ascontiguousarray(indices))
    if device.type != "cuda":
        return idx
    return idx.pin_memory().to(device, non_blocking=True)


def rng_state(device) -> dict:
    """torch's random generators that a training on ``device`` draws from, for a checkpoint: ``torch_rng`` (the
    CPU's) and ``cuda_rng`` (the GPU's, None off a GPU)."""
    import torch

    return {"torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state(device) if device.type == "cuda" else None}


def restore_rng_state(state: dict, device) -> None:
    """Put back the generators :func:`rng_state` saved in ``state`` (a checkpoint loaded to ``device``)."""
    import torch

    torch.set_rng_state(state["torch_rng"].cpu())  # map_location moved it to the training device
    if device.type == "cuda" and state.get("cuda_rng") is not None:
        torch.cuda.set_rng_state(state["cuda_rng"].cpu(), device)
