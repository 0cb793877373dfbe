"""The one step axis callbacks log on, so TensorBoard keeps every event."""


def validation_log_step(trainer) -> int:
    """The step Lightning logs validation metrics at: optimizer steps done, minus one (measured: after 60 steps the
    ``val/*`` scalars carry step 59). TensorBoard drops events older than a step it has already seen, so a callback
    that logged by epoch, or one step later, lost its earlier figures once steps counted optimizer steps."""
    return max(int(trainer.global_step) - 1, 0)

