"""compilation: compiled copies per concurrent call, graphs reused across constants of equal value, eager fallback."""

from __future__ import annotations

import threading
import warnings

import pytest
import torch

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
