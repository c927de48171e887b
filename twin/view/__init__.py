"""Watching a campaign: the observer, the Rerun recorder, `twin watch`/`replay`, the summary table."""
