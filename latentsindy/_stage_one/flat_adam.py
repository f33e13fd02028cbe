"""Adam and gradient-norm clipping on one flat buffer: the timeVAE's training step.

On a CPU the ``_foreach`` kernels of ``torch.optim.Adam(foreach=True)`` and
``clip_grad_norm_`` loop over the parameters one at a time: eight element-wise
operations on each of the timeVAE's 19 tensors every step, 0.55 ms of a 3.5 ms step on
prey-only LV. Here the parameters and their gradients are views into two flat buffers,
so each operation runs once over all of them. With float32 parameters on the CPU (the
default there) the clipping and the update are one compiled loop
(:func:`.step_kernels.adam`: 0.01 ms against torch's 0.05-0.11 ms), Adam's update
rounded in its own order (a test holds it to torch's within a few roundings over 200
steps). Elsewhere (``compiled=False``, a GPU) the arithmetic is Adam's foreach path
operation for operation (the same kernels in the same order, the clipping norm from
the same per-tensor norms), the same coefficients to the bit (a test holds it).
"""

from __future__ import annotations

import torch


class FlatAdam:
    """Adam (no weight decay, no amsgrad) with clipping, over parameters it flattens.

    On construction the parameters become views of one buffer and their ``.grad``
    views of another; :meth:`release` gives each its own storage again. Every
    parameter must receive a gradient at every step (Adam's step count is shared).
    ``compiled``: the compiled update (None: where the parameters are float32 on the
    CPU; True elsewhere is an error).

    Examples
    --------
    >>> import torch
    >>> w = torch.nn.Parameter(torch.ones(3))
    >>> opt = FlatAdam([w], lr=0.1)
    >>> opt.zero_grad(); (w**2).sum().backward(); opt.step(max_norm=1.0)
    >>> [round(v, 4) for v in w.tolist()]
    [0.9, 0.9, 0.9]
    >>> opt.release()
    """

    def __init__(self, params, lr: float, betas=(0.9, 0.999), eps: float = 1e-8,
                 compiled: bool | None = None):
        self.params = list(params)
        self.lr, (self.beta1, self.beta2), self.eps = lr, betas, eps
        on_cpu = all(p.device.type == "cpu" and p.dtype == torch.float32
                     for p in self.params)
        if compiled and not on_cpu:  # before the parameters are rebound
            dtypes = sorted({str(p.dtype) for p in self.params})
            devices = sorted({str(p.device) for p in self.params})
            raise ValueError("FlatAdam(compiled=True) needs float32 parameters on the CPU; "
                             f"got {', '.join(dtypes)} on {', '.join(devices)}.")
        self.compiled = on_cpu if compiled is None else compiled
        with torch.no_grad():
            self.flat = torch.cat([p.detach().reshape(-1) for p in self.params])
        self.grad = torch.zeros_like(self.flat)
        self.grads, offset = [], 0
        for p in self.params:
            n = p.numel()
            p.data = self.flat[offset:offset + n].view_as(p)
            p.grad = self.grad[offset:offset + n].view_as(p)
            self.grads.append(p.grad)
            offset += n
        self.exp_avg = torch.zeros_like(self.flat)
        self.exp_avg_sq = torch.zeros_like(self.flat)
        self.steps = 0
        if self.compiled:  # numpy views of the four buffers, for the compiled step
            from .step_kernels import adam  # numba: loaded at the first training

            self._adam = adam
            self._arrays = tuple(b.numpy() for b in (self.flat, self.grad, self.exp_avg,
                                                      self.exp_avg_sq))

    def zero_grad(self) -> None:
        """Zero the gradients in place (backward accumulates into the views)."""
        self.grad.zero_()

    def step(self, max_norm: float) -> None:
        """Clip the gradients to total 2-norm ``max_norm``, then one Adam step."""
        for p, g in zip(self.params, self.grads, strict=True):
            if p.grad is not g:
                raise RuntimeError("FlatAdam: a parameter's .grad was replaced (set to None "
                                   "or assigned); zero gradients with FlatAdam.zero_grad.")
        self.steps += 1
        if self.compiled:
            self._adam(*self._arrays, float(max_norm), float(self.lr), self.beta1,
                       self.beta2, self.eps, self.steps)
        else:
            with torch.no_grad():
                self._torch_step(max_norm)

    def _torch_step(self, max_norm):
        # clip_grad_norm_: the norm of the per-tensor norms, scaled by a clamped factor
        norms = torch._foreach_norm(self.grads, 2)
        total = torch.linalg.vector_norm(torch.stack(norms), 2)
        self.grad.mul_(torch.clamp(max_norm / (total + 1e-6), max=1.0))
        # torch.optim.Adam's _multi_tensor_adam (capturable=False), on the flat buffers
        self.exp_avg.lerp_(self.grad, 1 - self.beta1)
        self.exp_avg_sq.mul_(self.beta2)
        self.exp_avg_sq.addcmul_(self.grad, self.grad, value=1 - self.beta2)
        step = float(self.steps)
        bias1 = 1 - self.beta1 ** step
        bias2_sqrt = (1 - self.beta2 ** step) ** 0.5
        denom = self.exp_avg_sq.sqrt()
        denom.div_(bias2_sqrt)
        denom.add_(self.eps)
        self.flat.addcdiv_(self.exp_avg, denom, value=(self.lr / bias1) * -1)

    def release(self) -> None:
        """Give every parameter its own storage again and drop the gradients."""
        for p in self.params:
            p.data = p.data.clone()
            p.grad = None
