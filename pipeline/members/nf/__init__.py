"""The normalizing-flow members: one model (``model``) trained on the multi-wave prior, forecast
with as ``nf-growth`` (``growth``, daily cases), fine-tuned on real series as ``nf-real``
(``finetune``), and on weekly sources as ``nf-weekly`` (``weekly``)."""
