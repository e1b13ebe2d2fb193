"""The plant: the arm's joint dynamics (pure model) and the node that serves it on a bus."""
