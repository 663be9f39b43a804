"""Blind diagnosis of concealed effects over seeds: does ``diagnose`` find what was hidden?"""

from ._prove import CASES, detectability, run_prove

__all__ = ["CASES", "detectability", "run_prove"]
