"""``python -m agsf_torch.experiments.cli``: the ``agsf`` command."""

from .main import entry

entry()
