"""Loop health: the assessment of a control loop from its record (docs/health.md).

One entry point, :func:`autotuner.engine.health.assessment.assess`; one concept per module: the record, the
scales, the signals' half-cycles and noise, oscillation, sluggishness, stiction, variability, tracking, usage,
the sensor, the indices and the verdicts.
"""
