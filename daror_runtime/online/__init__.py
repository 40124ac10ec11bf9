"""Online validation (issue 29): indicators measured while the pilot uses the support."""
