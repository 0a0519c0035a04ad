"""The paper's formation controller (§2), slot assignment (eq. 33) and command limits."""
