"""Figures: matplotlib drawings of the robot and of results (Agg canvas, written atomically)."""
