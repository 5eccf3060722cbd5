"""Small self-contained experiments that check the method's claims on tasks with closed forms."""
