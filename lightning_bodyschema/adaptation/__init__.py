"""Adaptation as one pipeline (paper section III): prepare once per fault set, then per call
check postures -> encode -> the schema's ``adapt_normalized`` -> decode -> safe command -> physics check.

``BodySchema.adapt``/``adapter`` are the entry points; the steps are public so a controller can reuse them.
Never imports Lightning; takes the schema as an object with the ``BodySchema`` interface.
"""
from ..status import Status
from .command import AdaptationResult, command_status, safe_command
from .physics import flag_infeasible, mark_unchecked
from .pipeline import Adapter, check_postures

__all__ = ["Adapter", "AdaptationResult", "Status", "command_status", "safe_command", "flag_infeasible", "mark_unchecked",
           "check_postures"]
