"""torch's private internals are named in one module only (torchcal/_torch.py), and its wrappers hold, with and
without the private attribute they rely on."""

import re
from pathlib import Path

import pytest
import torch

import torchcal
from torchcal import _torch
from torchcal._torch import backward, plain, same_version, version_key
from torchcal.effects.base import Context
from torchcal.effects.kernel import KernelCorrection
from torchcal.filter._kalman import FlatModule, ModuleJacobian

F64 = torch.float64
PACKAGE = Path(__file__).resolve().parents[1] / "torchcal"
WRAPPER = PACKAGE / "_torch.py"
#: the private names the wrapper stands for (``torchcal._version``, the package's version module, is not one)
PRIVATE = [
    r"_functorch",
    r"is_functorch_wrapped",
    r"_execution_engine",
    r"run_backward",
    r"(?<!torchcal)\._version\b",
    r"[\"']_version[\"']",
    r"_torchcal_leaves",
]


def private_uses(root: Path) -> list[str]:
    """``file:line: text`` of every line of a .py file under ``root`` (but the wrapper) naming a private internal."""
    pattern = re.compile("|".join(PRIVATE))
    out = []
    for path in sorted(root.rglob("*.py")):
        if path.resolve() == WRAPPER:
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if pattern.search(line):
                out.append(f"{path.relative_to(root.parent)}:{n}: {line.strip()}")
    return out


def test_only_the_wrapper_names_torch_internals():
    found = private_uses(PACKAGE)
    assert not found, "private torch internals outside torchcal/_torch.py (use its wrappers):\n" + "\n".join(found)


def test_the_scan_sees_a_private_use(tmp_path):
    root = tmp_path / "torchcal"
    root.mkdir()
    (root / "a.py").write_text("from torchcal._version import __version__\nx = t._version\n")
    (root / "b.py").write_text("import torch\n\nf = torch._C._functorch.is_functorch_wrapped_tensor\n")
    assert private_uses(root) == [
        "torchcal/a.py:2: x = t._version",
        "torchcal/b.py:3: f = torch._C._functorch.is_functorch_wrapped_tensor",
    ]


def test_the_private_attributes_exist_in_this_torch():
    # the fallbacks are for another torch; this one should take the fast paths
    assert _torch._IS_WRAPPED is not None and _torch._ENGINE is not None


def test_plain_tells_a_transform_wrapper():
    x = torch.ones(3, dtype=F64)
    assert plain(x) and plain(x.requires_grad_(False)) and plain(torch.ones(3, requires_grad=True))
    seen = []
    torch.func.vmap(lambda t: seen.append(plain(t)) or t)(torch.ones(2, 3))
    torch.func.jvp(lambda t: seen.append(plain(t)) or t, (x,), (x,))
    torch.func.grad(lambda t: seen.append(plain(t)) or t.sum())(x)
    assert seen == [False, False, False]


def test_version_key():
    a, b = torch.zeros(3), torch.ones(2)
    key = version_key(a, None, b)
    assert len(key) == 2 and same_version(key, version_key(a, b))
    assert not same_version(key, version_key(a.clone(), b))  # an equal tensor is another object
    assert not same_version(key, version_key(a))
    a.add_(1.0)  # changed in place
    assert not same_version(key, version_key(a, b))
    assert not same_version(None, None) and not same_version(key, None)
    keys = []
    torch.func.vmap(lambda t: keys.append(version_key(t)) or t)(torch.ones(2, 3))
    assert keys == [None]


def test_fallbacks_without_the_functorch_check(monkeypatch):
    monkeypatch.setattr(_torch, "_IS_WRAPPED", None)
    x = torch.zeros(3)
    assert not plain(x) and version_key(x) is None


class _NoVersion(torch.Tensor):
    @property
    def _version(self):
        raise AttributeError("_version")


def test_fallback_without_a_version_counter():
    x = torch.zeros(3).as_subclass(_NoVersion)
    assert plain(x) and version_key(x) is None and version_key(None) == ()


@pytest.mark.parametrize("engine", [True, False])
def test_backward_equals_the_public_one(monkeypatch, engine):
    if not engine:
        monkeypatch.setattr(_torch, "_ENGINE", None)
    w = torch.tensor([0.3, -1.2, 2.0], dtype=F64, requires_grad=True)
    cot = torch.tensor([1.0, 2.0], dtype=F64)

    def out():
        return torch.stack([(w.sin() * w).sum(), w.prod()])

    g = out()
    backward(g, cot, True)
    backward(g, cot, False)  # the graph was retained for this second pass
    ours = w.grad.clone()
    w.grad = None
    g = out()
    torch.autograd.backward(g, cot, retain_graph=True)
    torch.autograd.backward(g, cot)
    assert torch.equal(ours, w.grad)


def _kernel_effect() -> KernelCorrection:
    g = torch.Generator().manual_seed(0)
    eff = KernelCorrection(6, 20)
    eff.support.copy_(torch.rand(20, 6, dtype=F64, generator=g))
    eff.alpha.copy_(torch.randn(20, 3, dtype=F64, generator=g) * 1e-4)
    return eff


@pytest.mark.parametrize("private", [True, False])
def test_kernel_correction_reuses_its_result_only_where_it_may(monkeypatch, private):
    if not private:
        monkeypatch.setattr(_torch, "_IS_WRAPPED", None)
    eff = _kernel_effect()
    q = torch.rand(7, 6, dtype=F64, generator=torch.Generator().manual_seed(1))
    first = eff(None, Context(q=q))
    assert torch.equal(first, eff.kernel(q) @ eff.alpha)
    assert (eff(None, Context(q=q)) is first) == private  # without the check nothing is reused
    q.add_(0.1)
    assert torch.equal(eff(None, Context(q=q)), eff.kernel(q) @ eff.alpha)
    # under a transform: computed, never kept
    eff._cache = None
    value = torch.func.vmap(lambda x: eff(None, Context(q=x)))(q[None])[0]
    assert torch.allclose(value, eff.kernel(q) @ eff.alpha, rtol=1e-12, atol=0) and eff._cache is None


def test_static_torques_without_the_functorch_check(monkeypatch):
    monkeypatch.setattr(_torch, "_IS_WRAPPED", None)
    robot = torchcal.load_robot("ur10")
    q = torch.rand(5, 6, dtype=F64, generator=torch.Generator().manual_seed(2))
    tau = robot.static_torques(q, payload=1.5)
    assert torch.equal(tau, robot.gravity_torques(q, payload=1.5).detach()) and not tau.requires_grad
    assert robot.static_torques(q, payload=1.5) is not tau and not robot.__dict__.get("_torque_cache")


def test_module_jacobian_rebinds_without_marking_the_modules():
    with torch.random.fork_rng():
        torch.manual_seed(3)
        net = torch.nn.Sequential(torch.nn.Linear(6, 5, dtype=F64), torch.nn.Tanh(), torch.nn.Linear(5, 3, dtype=F64))
    before = [set(vars(m)) for m in net.modules()]
    n = sum(p.numel() for p in net.parameters())
    q = torch.rand(1, 4, 6, dtype=F64)
    R = torch.linalg.qr(torch.randn(3, 3, dtype=F64))[0]
    w1 = torch.nn.utils.parameters_to_vector(net.parameters()).detach()[None].clone()
    w2 = w1 * 1.1
    step = ModuleJacobian(FlatModule(net, 6), q, R, 1)
    step(w1, 0)
    g2, H2 = step(w2, 2)  # another weight tensor: the copies are bound again
    g2_fresh, H2_fresh = ModuleJacobian(FlatModule(net, 6), q, R, 1)(w2, 2)
    assert torch.equal(g2, g2_fresh) and torch.equal(H2, H2_fresh)
    assert H2.shape == (1, 3, n + 3)
    assert [set(vars(m)) for m in net.modules()] == before  # the user's module is not written to
    # the copies hold the leaves in place of their parameters, and nothing else of the filter's
    for c in step.copies:
        for m, original in zip(c.modules(), net.modules()):
            assert set(vars(m)) - set(vars(original)) == {n for n, _ in original.named_parameters(recurse=False)}
