"""The same closed system written another way: hidden states shifted by observed
functions (``gauge``), a hidden state and its rate as one state with a conserved
constant (``first_integral``), a hidden state that is a function of the observed ones
substituted away (``observed_function``)."""
