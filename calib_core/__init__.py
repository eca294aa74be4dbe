"""Pure numerics of mimucal: models, estimators, simulator, diagnostics. No file or network I/O."""
