"""``--set key=value`` overrides: an unknown key is refused with the list of valid keys."""

from __future__ import annotations

import dataclasses

import pytest

from agsf_torch.experiments.config.loader import ExperimentConfig, parse_override


def test_unknown_key_lists_every_known_key():
    with pytest.raises(ValueError, match=r"unknown config key 'sigma_q' in override 'sigma_q=1' \(known: ") as info:
        parse_override("sigma_q=1")
    listed = str(info.value).split("(known: ", 1)[1].rstrip(")").split(", ")
    assert listed == sorted(f.name for f in dataclasses.fields(ExperimentConfig))


def test_known_key_is_parsed():
    assert parse_override(" runs = 3") == ("runs", 3)


@pytest.mark.parametrize(
    ("item", "problem"),
    [
        ("filters=[GSFF]", "Invalid value"),  # the shell removed the quotes of '["GSFF"]'
        ('faults=[{kind="star_outage", start=1.0, end=2.0]', "Unclosed inline table"),
        ('name="abc', "Unterminated string"),
    ],
)
def test_a_value_that_begins_as_toml_and_is_not_is_refused_with_the_parser_message(item, problem):
    """Such a value had been taken as a bare string, and the refusal that followed suggested quoting that string."""
    key = item.split("=", 1)[0]
    with pytest.raises(
        ValueError, match=rf"the value of '{key}' .* is not valid TOML \({problem}.*one level of quotes"
    ):
        parse_override(item)
    assert parse_override("star_noise_model=tangent") == ("star_noise_model", "tangent")  # a bare word stays a string
