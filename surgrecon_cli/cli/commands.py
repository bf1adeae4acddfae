"""The list of subcommands; each lives in its own `cmd_*.py` module."""

from __future__ import annotations

from .cmd_build_template import build_template_cmd
from .cmd_classify import classify_cmd
from .cmd_compare import compare_cmd
from .cmd_config import config_cmd
from .cmd_convert import convert_cmd
from .cmd_evaluate import evaluate_cmd
from .cmd_export import export_cmd
from .cmd_fit_tools import fit_tools_cmd
from .cmd_info import info_cmd
from .cmd_ingest import ingest_cmd
from .cmd_measure import measure_cmd
from .cmd_register import register_cmd
from .cmd_register_pair import register_pair_cmd
from .cmd_report import report_cmd
from .cmd_run import run_cmd
from .cmd_simulate import simulate_cmd

ALL = [build_template_cmd, classify_cmd, compare_cmd, config_cmd, convert_cmd, evaluate_cmd,
       export_cmd, fit_tools_cmd, info_cmd, ingest_cmd, measure_cmd, register_cmd,
       register_pair_cmd, report_cmd, run_cmd, simulate_cmd]
