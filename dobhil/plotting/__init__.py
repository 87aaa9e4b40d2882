"""PNG figures (matplotlib, Agg backend, imported only when a plot is asked for)."""
