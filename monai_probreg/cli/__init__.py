"""The ``monai-probreg`` command (``main``): its arguments, the lines it prints (``messages``) and ``apply``, around
the registration of :mod:`monai_probreg.registration`; the training folders moved into a template's space through
the command's code path (``template_space``, ``synth_space``). Nothing here is imported at ``import monai_probreg``:
the command imports what it needs, when it needs it.
"""
