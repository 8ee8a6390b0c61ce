"""Seed studies: simulate a robot, identify it with the pipelines, compare with the truth. They sit
to the right of both :mod:`torchcal.sim` and :mod:`torchcal.pipelines`, so that identifying code
never imports a simulator."""
