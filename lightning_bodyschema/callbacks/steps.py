"""The one step axis callbacks log on, so TensorBoard keeps every event."""


def validation_log_step(trainer) -> int:
    """The step Lightning logs validation metrics at: optimizer steps done, minus one (after 60 steps
    the ``val/*`` scalars carry step 59). TensorBoard drops events older than a step it has already seen, so a callback
    that logged by epoch, or one step later, lost its earlier figures once steps counted optimizer steps."""
    return max(int(trainer.global_step) - 1, 0)



def stopped_after_last_validation(trainer, validated_at, done_at) -> bool:
    """In ``on_train_end``: EarlyStopping requested the stop after the callbacks' validation hooks of the fit's last
    validation (logged at ``validated_at``), and the end-of-fit work was not done there (``done_at``)."""
    return trainer.should_stop and validated_at == validation_log_step(trainer) != done_at


def averaged_weights_now(trainer, pl_module) -> None:
    """In ``on_train_end``: give the schema its averaged weights now, as Lightning's ``WeightAveraging`` callbacks
    (EMA, SWA; ordered after ours by ``training.fit_loop.weight_averaging_last``) do in their own ``on_train_end``
    (a copy from the average, the same when repeated), so what is scored at the end of a fit is what is saved."""
    from lightning.pytorch.callbacks import WeightAveraging

    for callback in trainer.callbacks:
        if isinstance(callback, WeightAveraging):
            callback.on_train_end(trainer, pl_module)
