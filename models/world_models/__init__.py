"""World models: state (MLP) and visual (EDM) dynamics under one LightningModule, and their open-loop evaluations."""
