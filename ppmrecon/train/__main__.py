"""``python -m ppmrecon.train`` = ``ppmrecon-train`` (what ``torchrun -m`` starts)."""

from .cli import entry

entry()
