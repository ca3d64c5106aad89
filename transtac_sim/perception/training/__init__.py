"""Training the learned marker detector on generated datasets: targets, augmentation, loss, the loop."""
