"""export stage: a composed OpenUSD scene (usd-core)."""
