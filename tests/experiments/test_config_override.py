"""``--set key=value`` overrides: an unknown key is refused with the list of valid keys."""

from __future__ import annotations

import dataclasses

import pytest

from agsf_torch.experiments.config import ExperimentConfig, parse_override


def test_unknown_key_lists_every_known_key():
    with pytest.raises(ValueError, match=r"unknown config key 'sigma_q' in override 'sigma_q=1' \(known: ") as info:
        parse_override("sigma_q=1")
    listed = str(info.value).split("(known: ", 1)[1].rstrip(")").split(", ")
    assert listed == sorted(f.name for f in dataclasses.fields(ExperimentConfig))


def test_known_key_is_parsed():
    assert parse_override(" runs = 3") == ("runs", 3)
