"""Lightning callbacks: progress, figures, fault benchmarks, a validation at the end of every fit.

They hold no maths (they call evaluation/)."""
from .fault_benchmark import FaultBenchmark
from .figures import ReconstructionFigure
from .final_validation import FinalValidation
from .init_from import InitFrom
from .progress import EpochProgressBar

__all__ = ["EpochProgressBar", "FaultBenchmark", "FinalValidation", "InitFrom", "ReconstructionFigure"]
