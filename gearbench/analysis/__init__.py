"""Pure numerical analysis: identification, Kt, efficiency, diagnosis. No I/O."""

# The version of each identification/efficiency method, recorded in result.json beside
# gearbench's own version. Bump a method's version whenever it gives different numbers
# for the same recorded data, so re-analysed and archived results can be told apart.
METHOD_VERSIONS = {"default": "1", "paper": "1"}
