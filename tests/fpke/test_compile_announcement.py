"""The FPKE kernel's torch.compile compilation is announced (INFO, ``agsf_torch`` logger) when it starts."""

from __future__ import annotations

import logging

import pytest
import torch

from agsf_torch.fpke import matrices


def _fake_compile(calls: list[str]):
    """A stand-in for ``torch.compile`` (no real compilation in a unit test) recording its calls."""

    def compile(fn):
        def compiled(*args):
            calls.append(fn.__name__)
            return fn(*args)

        return compiled

    return compile


def test_compilation_is_announced_once_when_the_first_call_starts(monkeypatch, caplog):
    calls: list[str] = []
    monkeypatch.setattr(torch, "compile", _fake_compile(calls))
    monkeypatch.setattr(matrices, "_COMPILED", {})
    monkeypatch.setattr(matrices, "_pair_chunk", lambda *args: sum(args))
    caplog.set_level(logging.INFO, logger="agsf_torch")

    kernel = matrices._kernel("pair", compile=True)
    assert caplog.records == [], "nothing is announced before compilation starts"
    assert matrices._kernel("pair", compile=True) is kernel  # once per process

    assert kernel(1, 2) == 3
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2, messages
    assert messages[0].startswith("compiling the FPKE kernel 'pair' with torch.compile")
    assert messages[1].startswith("compiled the FPKE kernel 'pair' in ")
    assert all(r.levelno == logging.INFO and r.name.startswith("agsf_torch") for r in caplog.records)

    caplog.clear()
    assert kernel(3, 4) == 7
    assert caplog.records == [], "later calls are silent"
    assert len(calls) == 2


def test_eager_kernels_announce_nothing(caplog):
    caplog.set_level(logging.INFO, logger="agsf_torch")
    assert matrices._kernel("galerkin", compile=False) is matrices._galerkin_chunk
    assert caplog.records == []


def test_a_failed_first_call_announces_again_on_the_next(monkeypatch, caplog):
    monkeypatch.setattr(torch, "compile", _fake_compile([]))
    monkeypatch.setattr(matrices, "_COMPILED", {})
    state = {"fail": True}

    def chunk(*args):
        if state["fail"]:
            raise RuntimeError("boom")
        return 0

    monkeypatch.setattr(matrices, "_product_chunk", chunk)
    caplog.set_level(logging.INFO, logger="agsf_torch")
    kernel = matrices._kernel("product", compile=True)
    with pytest.raises(RuntimeError, match="boom"):
        kernel()
    assert [r.getMessage().split(" the ")[0] for r in caplog.records] == ["compiling"]  # no "compiled" after a failure
    state["fail"] = False
    caplog.clear()
    assert kernel() == 0
    assert [r.getMessage().split(" the ")[0] for r in caplog.records] == ["compiling", "compiled"]
