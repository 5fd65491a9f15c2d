"""Self-supervised training: homographies, homographic adaptation, label store, pairs, losses, trainer."""
