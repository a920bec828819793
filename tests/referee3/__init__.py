"""Third close-the-loop referee: an independent generator family and its scorer."""
