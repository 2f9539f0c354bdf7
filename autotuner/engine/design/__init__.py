"""Gains from an identified point: the robust design, the classical rules, robustness measures and closed-loop checks."""
