"""Closing the loop with measured data (ROS-free): the residual of the current model against a
reference, a catalogue of physical effects the model may lack, their identification on held-out
time blocks of a session of logs, the extended model, the report; and ISO 230-2 evaluation of an
axis.

    runs = [read_run('x.mcap'), read_run('c.mcap'), read_run('motion.mcap')]
    result = analyze(runs)                # effects found, leave-one-run-out before and after
    write_report(result, 'out/analysis')  # report.md, analysis.json, figures, model.yaml
"""

from mmd_ros.analysis.effects import CATALOGUE, Effect, Parameter, catalogue
from mmd_ros.analysis.errors import AnalysisError
from mmd_ros.analysis.identify import (
    Analysis, AnalysisOptions, Candidate, ComponentError, Found, RunSummary, Unchecked, analyze,
    component_errors,
)
from mmd_ros.analysis.iso230 import IsoResult, detect_dwells, evaluate, evaluate_run
from mmd_ros.analysis.report import format_summary, write_report

__all__ = [
    'Analysis', 'AnalysisError', 'AnalysisOptions', 'CATALOGUE', 'Candidate', 'ComponentError',
    'Effect', 'Found', 'IsoResult', 'Parameter', 'RunSummary', 'Unchecked', 'analyze', 'catalogue',
    'component_errors',
    'detect_dwells', 'evaluate', 'evaluate_run', 'format_summary', 'write_report',
]
