"""The scene plan: what a scene needs, decided from measurements of its training views (docs/plan.md)."""
