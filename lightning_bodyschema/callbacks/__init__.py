"""Lightning callbacks: progress, figures, fault benchmarks. They hold no maths (they call evaluation/)."""
from .figures import ReconstructionFigure
from .progress import EpochProgressBar

__all__ = ["EpochProgressBar", "ReconstructionFigure"]
