"""compilation: compiled copies per concurrent call, graphs reused across constants of equal value, eager fallback."""

from __future__ import annotations

import threading
import warnings
from collections import Counter

import pytest
import torch

from hydrosoft import compilation
from hydrosoft.compilation import CompiledFunction, signature


def scaled_norm(x: torch.Tensor, pair: tuple[torch.Tensor, torch.Tensor], gain: float) -> torch.Tensor:
    """A small pure function of a tensor, a pytree of tensors and a constant."""
    return gain * (x * pair[0] + pair[1]).square().sum(-1).sqrt()


def test_a_failing_compiler_warns_once_and_the_eager_function_answers():
    def broken_backend(graph, example_inputs):
        raise RuntimeError("no compiler here")

    fast = CompiledFunction(scaled_norm, backend=broken_backend)
    x, pair = torch.randn(4, 3), (torch.randn(3), torch.randn(3))
    with pytest.warns(RuntimeWarning, match="running eager"):
        out = fast(x, pair, 2.0)
    assert not fast.compiled and "no compiler here" in fast.fallback_reason
    assert torch.equal(out, scaled_norm(x, pair, 2.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast(x, pair, 2.0)  # warns once only


def test_the_signature_tells_apart_what_compiles_apart():
    x, pair = torch.randn(4, 3), (torch.randn(3), torch.randn(3))
    key = signature(x, pair, 2.0)
    assert key == signature(torch.randn(4, 3), (torch.randn(3), torch.randn(3)), 2.0)  # new values, same graph
    assert key != signature(x, pair, 3.0)  # a constant is baked in
    assert key != signature(x.t().contiguous().t(), pair, 2.0)  # strides
    assert key != signature(x, (pair[0], None), 2.0)  # an absent tensor
    with torch.no_grad():
        assert key != signature(x, pair, 2.0)


def test_default_options_are_chosen_per_device_and_given_options_are_kept():
    """The CPU's graphs get inductor's C++ wrapper; a GPU's do not (its C++ wrapper is a build of its own per graph),
    and neither gets bounds checks; a caller's mode, options or other backend are left as given."""
    cpu = compilation.with_default_options({"dynamic": False})
    assert cpu == {"dynamic": False, "options": compilation.DEFAULT_OPTIONS} and cpu["options"]["cpp_wrapper"]
    assert compilation.with_default_options({}, torch.device("cpu")) == {"options": compilation.DEFAULT_OPTIONS}
    for device in ("cuda", "cuda:1", torch.device("cuda", 0)):
        gpu = compilation.with_default_options({"dynamic": False}, device)["options"]
        assert "cpp_wrapper" not in gpu and not gpu["assert_indirect_indexing"] and gpu["triton.cudagraphs"]
        assert not any(key.startswith("cpp.") for key in gpu)
    for given in ({"mode": "reduce-overhead"}, {"options": {"cpp_wrapper": False}}, {"backend": "eager"}):
        assert compilation.with_default_options(given, "cuda") == given


def test_with_cuda_graphs_each_output_is_copied_out_of_the_graphs_memory(monkeypatch):
    """Copies that run CUDA graphs return copies of their tensors (a graph's next replay overwrites its outputs);
    others return the compiled function's own. (An identity function shows which: its output is its input.) A GPU's
    default options run CUDA graphs, as do reduce-overhead and the process's inductor setting; the CPU's do not."""
    x = torch.randn(3)
    identity = lambda t, pair: (t, [pair[0]])  # noqa: E731
    plain = compilation.CompiledCopies(lambda: identity, compilation._call)
    assert plain.run((x, (x,)), compilation._call, identity)[0].data_ptr() == x.data_ptr()
    copying = compilation.CompiledCopies(lambda: identity, compilation._call, copy_outputs=True)
    same, [other] = copying.run((x, (x,)), compilation._call, identity)
    assert same.data_ptr() != x.data_ptr() and other.data_ptr() != x.data_ptr()
    assert torch.equal(same, x) and torch.equal(other, x)
    assert CompiledFunction(identity, device="cuda")._copies._copy_outputs  # a GPU's defaults: CUDA graphs
    assert not CompiledFunction(identity)._copies._copy_outputs
    uses = compilation.uses_cuda_graphs
    assert uses(compilation.with_default_options({}, "cuda")) and uses({"mode": "reduce-overhead"})
    assert not uses(compilation.with_default_options({}, "cpu")) and not uses({"backend": "eager"})
    monkeypatch.setattr(torch._inductor.config.triton, "cudagraphs", True)
    assert uses(compilation.with_default_options({}, "cpu")) and not uses({"backend": "eager"})


def test_calls_at_once_from_threads_each_run_a_copy_of_their_own_and_agree_with_eager(fresh_dynamo):
    fast = CompiledFunction(scaled_norm, backend="eager")
    x, pair = torch.randn(5, 3), (torch.randn(3), torch.randn(3))
    expected = scaled_norm(x, pair, 0.5)
    start, results, errors = threading.Barrier(3), [], []

    def call() -> None:
        try:
            start.wait(timeout=60)
            results.append(fast(x, pair, 0.5))
        except BaseException as error:  # noqa: BLE001 - reported by the test
            errors.append(error)

    threads = [threading.Thread(target=call) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not errors and len(results) == 3, errors
    assert fast.compiled and len(fast._copies.copies) == 3
    for out in results:
        torch.testing.assert_close(out, expected, rtol=0, atol=0)
    counters = torch._dynamo.utils.counters
    before = counters["stats"]["unique_graphs"]
    fast(torch.randn(5, 3), (torch.randn(3), torch.randn(3)), 0.5)  # later calls, one at a time: no new graph
    assert counters["stats"]["unique_graphs"] == before and len(fast._copies.copies) == 3


def test_a_copy_made_later_compiles_every_signature_seen_before_it_runs(fresh_dynamo):
    """Solver workers take whichever copy is idle, so one copy may miss a signature that another ran; it then
    compiled the first time both were needed at once, in the middle of a run. A copy now catches up, on the kept
    examples, as soon as it is checked out: here a second copy, made while the first is busy, compiles both
    signatures before its first call, and then runs either without compiling."""
    fast = CompiledFunction(scaled_norm, backend="eager")
    copies = fast._copies
    x, pair = torch.randn(4, 3), (torch.randn(3), torch.randn(3))
    with torch.no_grad():
        fast(x, pair, 2.0)
    fast(x.clone().requires_grad_(True), pair, 2.0)
    assert len(copies.copies) == 1 and len(copies._examples) == 2
    first = copies._check_out()  # busy: the next call needs a new copy
    counters = torch._dynamo.utils.counters
    before = counters["stats"]["unique_graphs"]
    with torch.no_grad():
        out = fast(x, pair, 2.0)
    assert len(copies.copies) == 2 and counters["stats"]["unique_graphs"] - before == 2
    second = copies.copies[1]
    assert second.warm == first.warm == set(copies._examples)
    torch.testing.assert_close(out, scaled_norm(x, pair, 2.0), rtol=0, atol=0)
    before = counters["stats"]["unique_graphs"]
    leaf = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(fast(leaf, pair, 2.0).sum(), leaf)  # the second copy, already compiled
    assert counters["stats"]["unique_graphs"] == before and torch.isfinite(grad).all()
    copies._idle.append(first)


def test_each_signature_compiles_on_as_many_copies_as_workers_when_it_first_appears(fresh_dynamo):
    """With ``workers = 3`` the first call of each signature leaves three copies compiled for it, so that three
    workers calling at once later compile nothing."""
    fast = CompiledFunction(scaled_norm, workers=3, backend="eager")
    x, pair = torch.randn(4, 3), (torch.randn(3), torch.randn(3))
    counters = torch._dynamo.utils.counters
    before = counters["stats"]["unique_graphs"]
    fast(x, pair, 2.0)
    with torch.no_grad():
        fast(x, pair, 2.0)
    assert counters["stats"]["unique_graphs"] - before == 6
    assert len(fast._copies.copies) == 3 and all(len(copy.warm) == 2 for copy in fast._copies.copies)
    held = [fast._copies._check_out() for _ in range(2)]  # two workers busy: a third call takes the third copy
    before = counters["stats"]["unique_graphs"]
    fast(x, pair, 2.0)
    assert counters["stats"]["unique_graphs"] == before and len(fast._copies.copies) == 3
    fast._copies._idle.extend(held)


def closing_over(weights: torch.Tensor):
    """A function of ``x`` that closes over ``weights`` (as the compiled step closes over its model)."""
    def weighted(x: torch.Tensor, gain: float) -> torch.Tensor:
        return gain * torch.tanh(x @ weights).square().sum(-1)

    return weighted


def test_a_precompiled_function_is_built_then_loaded_with_the_loaders_closure_and_agrees(tmp_path, monkeypatch,
                                                                                        fresh_dynamo):
    """``hydrosoft-stack compile`` builds (``build``), a launch only loads: it computes with its own closure (the
    model), agrees with eager forward and backward, and compiles a signature without a file the usual way."""
    monkeypatch.setattr(compilation, "PRECOMPILED", Counter())
    try:
        compilation.use_precompiled(tmp_path, build=True)
        first = CompiledFunction(closing_over(torch.linspace(-1.0, 1.0, 12).reshape(3, 4)), options={})
        compilation.use_precompiled(tmp_path)
        later_weights = torch.linspace(0.5, -0.5, 12).reshape(3, 4)  # what a later process's model holds
        later = CompiledFunction(closing_over(later_weights), options={})
    finally:
        compilation.use_precompiled(None)
    x = torch.randn(5, 3, requires_grad=True)
    first(x, 2.0).sum().backward()
    assert compilation.PRECOMPILED == {"built": 1}
    assert len(list(tmp_path.glob("*.pt2"))) == 1
    x.grad = None
    torch._dynamo.reset()  # nothing of dynamo's is left to trace from: the file alone serves
    out = later(x, 2.0)
    out.sum().backward()
    assert compilation.PRECOMPILED == {"built": 1, "loaded": 1}
    grad, x.grad = x.grad, None
    eager = closing_over(later_weights)(x, 2.0)
    eager.sum().backward()
    torch.testing.assert_close(out, eager)  # float32 tolerance, with the later closure's weights
    torch.testing.assert_close(grad, x.grad)
    with torch.no_grad():  # another signature (grad mode) without a file: traced, nothing built
        torch.testing.assert_close(later(x, 2.0), eager.detach())
    assert compilation.PRECOMPILED == {"built": 1, "loaded": 1, "jit": 1} and later.compiled
    assert len(list(tmp_path.glob("*.pt2"))) == 1
