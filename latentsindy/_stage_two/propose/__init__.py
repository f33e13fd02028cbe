"""Hypotheses: structures that could explain the data, each with the hidden series it
implies (``smoother``) and a cheap closure (``closure``); ``proposal`` evaluates one
structure (cached per context), ``hypotheses`` proposes and ranks them, ``nested`` adds
a hidden state inside a hidden state's equation."""
