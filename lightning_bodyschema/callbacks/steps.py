"""The one step axis callbacks log on, so TensorBoard keeps every event."""


def validation_log_step(trainer) -> int:
    """The step Lightning logs validation metrics at: optimizer steps done, minus one (measured: after 60 steps the
    ``val/*`` scalars carry step 59). TensorBoard drops events older than a step it has already seen, so a callback
    that logged by epoch, or one step later, lost its earlier figures once steps counted optimizer steps."""
    return max(int(trainer.global_step) - 1, 0)


def fit_ends_with_this_validation(trainer) -> bool:
    """True at a validation after which the fit stops: the last epoch of ``max_epochs``, ``max_steps`` reached (also
    inside an epoch), or a stop requested (EarlyStopping). ``max_epochs=-1`` (endless) never ends by epochs."""
    by_epochs = trainer.max_epochs is not None and trainer.max_epochs > 0 and trainer.current_epoch + 1 >= trainer.max_epochs
    by_steps = trainer.max_steps is not None and trainer.max_steps > 0 and trainer.global_step >= trainer.max_steps
    return bool(by_epochs or by_steps or trainer.should_stop)
