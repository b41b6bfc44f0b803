"""The demo's steps: one module per step, each with a ``run(ctx) -> results`` function."""
