"""The learned descriptors' recipes: one folder per model family (buffer/, spinnet/, fcgf_lite/) with its
model card, networks, export, quantisation, benchmark and records; evaluate.py is shared by the families.
Not part of the installed package: the runtime front ends are fastmac_exp.descriptors and the shipped models
are package data in fastmac_exp/models/. A regular package (not a namespace one), so that
`descriptors.<family>.<script>` always resolves here, never to another `descriptors` on sys.path."""
