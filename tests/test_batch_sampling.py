"""Training batches: windows of views, and sub-windows of a batch (the latent update's crop)."""

import torch

from rainyscape.cameras import Window
from rainyscape.engine.sampling import gather_pixels, sample_windows


def _images(n=3, h=20, w=24):
    g = torch.Generator().manual_seed(0)
    return torch.randint(0, 256, (n, h, w, 3), generator=g, dtype=torch.uint8)


def test_windows_stay_inside_and_gather_their_pixels():
    images = _images()
    g = torch.Generator().manual_seed(1)
    views, win = sample_windows(torch.arange(3), 4, 8, 24, 20, g)
    assert (win.x0 + 8 <= 24).all() and (win.y0 + 8 <= 20).all()
    patch = gather_pixels(images, views, win)
    b = 2
    y, x, v = int(win.y0[b]), int(win.x0[b]), int(views[b])
    assert torch.equal(patch[b], images[v, y:y + 8, x:x + 8].permute(2, 0, 1).float() / 255)


def test_whole_view_when_size_is_zero():
    views, win = sample_windows(torch.arange(3), 2, 0, 24, 20, torch.Generator().manual_seed(0))
    assert (win.width, win.height) == (24, 20) and int(win.x0.abs().sum() + win.y0.abs().sum()) == 0


def test_subwindow_crop_cuts_the_same_pixels_as_its_window():
    images = _images()
    g = torch.Generator().manual_seed(2)
    views, win = sample_windows(torch.arange(3), 2, 16, 24, 20, g)
    target = gather_pixels(images, views, win)
    rendered, rain = target * 0.5, target * 0.25
    sub = win.random_subwindow(6, g)
    local = sub.relative_to(win)
    assert (sub.width, sub.height) == (6, 6)
    assert (sub.x0 >= win.x0).all() and (sub.x0 + 6 <= win.x0 + 16).all()
    direct = gather_pixels(images, views, sub)  # absolute offsets index the full images
    assert torch.equal(local.crop(target), direct)
    assert torch.equal(local.crop(rendered), direct * 0.5) and torch.equal(local.crop(rain), direct * 0.25)
    assert isinstance(sub, Window)
