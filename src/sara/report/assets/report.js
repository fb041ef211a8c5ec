(function () {
  document.querySelectorAll('.legend').forEach(function (legend) {
    var svg = document.getElementById(legend.getAttribute('data-for'));
    if (!svg) { return; }
    legend.querySelectorAll('input[data-role]').forEach(function (box) {
      box.addEventListener('change', function () {
        svg.querySelectorAll('.role-' + box.getAttribute('data-role')).forEach(function (g) {
          g.style.display = box.checked ? '' : 'none';
        });
      });
    });
  });
})();
