"""Model refinement: residuals, effect library, sparse selection, refined system, report."""
