"""Matchers: the plug-ins that verify a query's top candidates (method.md's optional, costly verification step).

Why a package: verification is one idea with one contract (``base.Matcher``, ``base.Verification``) and
several ways to do it (RootSIFT mutual nearest neighbours, LighterGlue, ...). Each matcher is one module of
this package that registers itself by name (``app.engine.registry``); a configuration names the one it uses
(``PipelineConfig.matcher``). What verification does with the outcome (``fusion.fused_score``) and the
geometry every matcher ends with (``geometry.fit_geometry``) live here too.
"""
