"""Lightning callbacks: progress, figures, fault benchmarks. They hold no maths (they call evaluation/)."""
from .fault_benchmark import FaultBenchmark
from .figures import ReconstructionFigure
from .init_from import InitFrom
from .progress import EpochProgressBar

__all__ = ["EpochProgressBar", "FaultBenchmark", "InitFrom", "ReconstructionFigure"]
