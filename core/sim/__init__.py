"""Team simulator (paper §4-5): leader profiles, follower unicycles, scenarios."""
